"""Camera paths of a user's scene (render-scene --frames N --move ...): the pose math, the errors for
bad values, and small renders whose recorded cameras follow the path."""
import json
import math

import numpy as np
import pytest

from mcdenoise.pipeline.config import ConfigError
from mcdenoise.pipeline.store import Store
from mcdenoise.render.camera import dolly_path, orbit_path, parse_move, rotation, sensor_path
from mcdenoise.render.external import camera_move
from tests.helpers import ORBIT_SCENE, TINY, cli, look_at


def test_orbit_keeps_the_target_centred_and_the_distance():
    start = look_at((0.0, 1.0, 4.0), (0.0, 0.0, 0.0), (0, 1, 0))
    distance = math.sqrt(17)
    path = orbit_path(start, distance, 10.0, 8)
    assert len(path) == 8 and np.array_equal(path[0][:3, :3], start[:3, :3])
    np.testing.assert_allclose(path[0], start, atol=1e-15)
    for k, pose in enumerate(path):
        to_target = -pose[:3, 3]
        np.testing.assert_allclose(np.linalg.norm(to_target), distance, rtol=1e-12)
        np.testing.assert_allclose(pose[:3, 2], to_target / distance, atol=1e-12)   # still looks at the target
        np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-12)
    # The whole orbit turns by 10 degrees about the camera's up axis through the target.
    cos = np.dot(path[0][:3, 2], path[-1][:3, 2])
    assert math.degrees(math.acos(min(cos, 1.0))) == pytest.approx(10.0, abs=1e-9)
    # Positive angles move the camera to its right (against its 'left' column).
    assert np.dot(path[1][:3, 3] - path[0][:3, 3], start[:3, 0]) < 0


def test_dolly_moves_along_the_view_axis():
    start = look_at((1.0, 2.0, 3.0), (0.0, 0.0, 0.0), (0, 1, 0))
    d = math.sqrt(14)
    path = dolly_path(start, d, 0.2, 5)
    np.testing.assert_allclose(np.linalg.norm(path[-1][:3, 3]), 0.8 * d, rtol=1e-12)
    for pose in path:
        np.testing.assert_array_equal(pose[:3, :3], start[:3, :3])
    steps = np.diff([p[:3, 3] for p in path], axis=0)
    np.testing.assert_allclose(steps, np.broadcast_to(steps[0], steps.shape), atol=1e-12)   # evenly


def test_sensor_path_interpolates_between_two_cameras():
    a = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), (0, 1, 0))
    b = look_at((5.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0, 1, 0))   # a quarter turn about y
    path = sensor_path(a, b, 3)
    np.testing.assert_allclose(path[0], a, atol=1e-12)
    np.testing.assert_allclose(path[-1], b, atol=1e-12)
    # Halfway: 45 degrees of the turn, the origin halfway along the straight line.
    np.testing.assert_allclose(path[1][:3, :3], rotation((0, 1, 0), math.radians(45)) @ a[:3, :3], atol=1e-12)
    np.testing.assert_allclose(path[1][:3, 3], [2.5, 0, 2.5], atol=1e-12)
    # A mirrored pair (negative determinant) is interpolated as its mirror image and stays mirrored.
    flip = np.diag([-1.0, 1, 1, 1])
    mirrored = sensor_path(a @ flip, b @ flip, 3)
    np.testing.assert_allclose(mirrored[1], path[1] @ flip, atol=1e-12)
    with pytest.raises(ValueError, match="handedness"):
        sensor_path(a, b @ flip, 3)


def test_sensor_path_ends_on_any_two_rotations():
    """The endpoints come back exactly (to round-off) for random rotations and half turns, whichever
    diagonal entry the quaternion conversion pivots on."""
    rng = np.random.default_rng(3)
    turns = [rotation(rng.normal(size=3), rng.uniform(-np.pi, np.pi)) for _ in range(20)]
    turns += [rotation(axis, np.pi) for axis in np.eye(3)]
    for r0, r1 in zip(turns, turns[1:] + turns[:1]):
        a, b = np.eye(4), np.eye(4)
        a[:3, :3], b[:3, :3], b[:3, 3] = r0, r1, [1, 2, 3]
        path = sensor_path(a, b, 4)
        np.testing.assert_allclose(path[0], a, atol=1e-12)
        np.testing.assert_allclose(path[-1], b, atol=1e-12)
        for pose in path:
            np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-12)


def test_move_values():
    assert parse_move("orbit:10") == ("orbit", 10.0) and parse_move("dolly:-0.5") == ("dolly", -0.5)
    assert camera_move(8, "dolly:.2") == {"kind": "dolly", "amount": 0.2, "frames": 8}
    assert camera_move(4, None) == {"kind": "sensors", "frames": 4} and camera_move(1, None) is None
    for frames, move, said in ((8, "spin:3", "expected orbit:DEGREES"), (8, "orbit:ten", "expected orbit"),
                               (8, "orbit:400", "at most 360"), (8, "dolly:1", "below 1"),
                               (1, "orbit:10", "needs --frames 2"), (0, None, "render 1 to 100 frames")):
        with pytest.raises(ConfigError, match=said) as err:
            camera_move(frames, move)
        assert "\n" not in str(err.value)



def test_a_bad_move_is_one_line_on_the_command_line(tmp_path):
    xml = tmp_path / "s.xml"
    xml.write_text(ORBIT_SCENE.format(second=""))
    proc = cli("render-scene", xml, "--frames", "3", "--move", "orbit:x", "--store", tmp_path / "st", "--config",
               TINY, check=False)
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0
    assert "--move 'orbit:x': expected orbit:DEGREES" in proc.stderr
    assert not (tmp_path / "st").exists()


def test_a_rerun_along_another_camera_path_is_refused(tmp_path):
    """Frame k's pose is k/(N-1) of the move and a rerun keeps the images on disk: render-scene refuses another
    frame count or move into the same scene folder, in one line naming the folder, both paths and the way out,
    and leaves the store as it was; the same command again resumes (nothing to render)."""
    xml = tmp_path / "s.xml"
    xml.write_text(ORBIT_SCENE.format(second=""))
    first = ["--frames", "2", "--move", "orbit:8"]
    common = ["--store", tmp_path / "st", "--resolution", "4x3", "--config", TINY, "dataset.stacks=1",
              "dataset.gt_spp=4"]
    cli("render-scene", xml, *first, *common)
    store = Store(tmp_path / "st")
    folder = store.scene_dir("ext_s")
    before = {p: p.read_bytes() for p in sorted((tmp_path / "st").rglob("*")) if p.is_file()}
    for other, said in ((["--frames", "3", "--move", "orbit:8"], "--frames 3 --move orbit:8"),
                        (["--frames", "2", "--move", "dolly:0.1"], "--frames 2 --move dolly:0.1"),
                        (["--frames", "2"], "--frames 2;"), ([], "--frames 1;")):
        proc = cli("render-scene", xml, *other, *common, check=False)
        assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0, proc.stderr
        assert f"{folder}: rendered with --frames 2 --move orbit:8, not {said}" in proc.stderr
        assert "delete the folder or give the scene another --name" in proc.stderr
        assert {p: p.read_bytes() for p in sorted((tmp_path / "st").rglob("*")) if p.is_file()} == before
    cli("render-scene", xml, *first, *common)
    assert sorted(p.name for p in folder.iterdir() if p.is_dir()) == ["000", "001"]
    frames = {p: data for p, data in before.items() if p.parent.parent == folder}   # images and frame.json
    assert len(frames) == 2 * 4 and all(p.read_bytes() == data for p, data in frames.items())


def test_seed_counters_stay_distinct_32_bit_values():
    """Frame f of external scene i seeds image k from (2^20 (1+f) + i) images + k: render-scene refuses a frame
    and stack count whose counters would pass 2^32, in one line saying both limits."""
    from mcdenoise.pipeline.store import image_names
    from mcdenoise.render.external import _EXTERNAL_INDEX_BASE, MAX_FRAMES, frame_seeds, seed_range

    seed_range(MAX_FRAMES, 38)
    images = len(image_names(38))
    top = (_EXTERNAL_INDEX_BASE * MAX_FRAMES + _EXTERNAL_INDEX_BASE - 1) * images + images - 1
    assert top < 1 << 32        # the last frame of the 2^20-th external scene still fits
    seeds = [s for f in range(MAX_FRAMES) for s in frame_seeds(0, _EXTERNAL_INDEX_BASE, f, image_names(38)).values()]
    assert len(set(seeds)) == len(seeds)
    with pytest.raises(ConfigError, match=r"--frames 100 with dataset.stacks=39: .* pass 2\^32 \(at most 98 "
                                          r"frames of 39 stacks, or 38 stacks of 100 frames\)") as err:
        seed_range(MAX_FRAMES, 39)
    assert "\n" not in str(err.value)


@pytest.mark.slow
def test_render_scene_orbits_and_the_frames_warp_onto_each_other(tmp_path):
    """Three frames orbiting a checkered sphere before a checkered wall by 30 degrees: frames 000..002 in
    the store, each camera on the orbit about the sphere's near point (the first surface on the view
    axis, |(0, 0.5, 4)| - 1 = 3.03 away), and GT1 of frame 1 warped into frame 2 matches frame 2 on the
    valid pixels far better than frame 1 unwarped (measured: 38.9 dB against 30.4 dB, 61 % valid; the
    warped PSNR is the two GTs' own noise at 64 spp)."""
    from mcdenoise.pipeline import metrics
    from mcdenoise.pipeline.motion import reproject, warp
    xml = tmp_path / "s.xml"
    xml.write_text(ORBIT_SCENE.format(second=""))
    cli("render-scene", xml, "--frames", "3", "--move", "orbit:30", "--store", tmp_path / "st", "--config", TINY)
    store = Store(tmp_path / "st")
    sm = store.scene_manifest("ext_s")
    assert sm["frames"] == 3 and sm["description"]["move"] == {"kind": "orbit", "amount": 30.0, "frames": 3}
    assert len({s for f in sm["seeds"].values() for s in f.values()}) == 3 * len(sm["images"])
    cams = [store.camera("ext_s", f) for f in range(3)]
    start = look_at((0, 0.5, 4), (0, 0, 0), (0, 1, 0))
    # frame.json rounds the matrix to 6 decimals; Mitsuba holds it in float32 (relative 6e-8).
    np.testing.assert_allclose(cams[0].camera_to_world, start, atol=2e-6)
    distance = float(np.linalg.norm([0, 0.5, 4])) - 1.0
    for cam, pose in zip(cams, orbit_path(start, distance, 30.0, 3)):
        np.testing.assert_allclose(cam.camera_to_world, pose, atol=1e-5)
        assert cam.fov_x == pytest.approx(45.0, abs=1e-4)
    prev, cur = (store.read_image("ext_s", f, "gt1", ["color", "depth", "normal"])[0] for f in (1, 2))
    xy, valid = reproject(cur["depth"], cams[2], cams[1], depth_prev=prev["depth"], normal_t=cur["normal"],
                          normal_prev=prev["normal"])
    assert valid.mean() > 0.5
    warped = metrics.psnr(warp(prev["color"], xy, valid)[valid], cur["color"][valid])
    still = metrics.psnr(prev["color"][valid], cur["color"][valid])
    print(f"orbit: valid {valid.mean():.2f}, warped {warped:.1f} dB, unwarped {still:.1f} dB")
    assert warped > still + 6
    # Every image of every frame carries the frame's camera in its header.
    from mcdenoise.pipeline.exr import read_camera
    for f in range(3):
        for name in sm["images"]:
            header_cam = read_camera(store.image_path("ext_s", f, name))
            np.testing.assert_allclose(header_cam.camera_to_world, cams[f].camera_to_world, atol=1e-5)


@pytest.mark.slow
def test_render_scene_goes_from_the_first_camera_to_the_second(tmp_path):
    xml = tmp_path / "two.xml"
    second = """<sensor type="perspective"><float name="fov" value="55"/>
    <transform name="to_world"><lookat origin="1, 0.5, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film></sensor>"""
    xml.write_text(ORBIT_SCENE.format(second=second))
    cli("render-scene", xml, "--frames", "2", "--store", tmp_path / "st", "--config", TINY, "dataset.stacks=1")
    store = Store(tmp_path / "st")
    cams = [store.camera("ext_two", f) for f in range(2)]
    np.testing.assert_allclose(cams[0].camera_to_world, look_at((0, 0.5, 4), (0, 0, 0), (0, 1, 0)), atol=2e-6)
    np.testing.assert_allclose(cams[1].camera_to_world, look_at((1, 0.5, 4), (0, 0, 0), (0, 1, 0)), atol=2e-6)
    assert (cams[0].fov_x, cams[1].fov_x) == (pytest.approx(45, abs=1e-4), pytest.approx(55, abs=1e-4))
    record = json.loads((store.frame_dir("ext_two", 1) / "frame.json").read_text())
    assert record["fov_x"] == pytest.approx(55, abs=1e-4) and record["near_clip"] > 0
