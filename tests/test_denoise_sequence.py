"""``denoise --sequence``: the file pattern, the outputs, the history from the headers' cameras, and frame by
frame (said in one line) where the EXRs carry no camera or one of another size than their pixels."""
import shutil

import numpy as np
import OpenEXR
import pytest

from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.exr import read_camera, read_header, read_layers
from mcdenoise.pipeline.motion import exr_matrices
from mcdenoise.train.sequence import frame_view, output_path, sequence_files

from .helpers import ORBIT_SCENE, TINY, cli, look_at, write_rgb_exr


def test_the_pattern_finds_the_frames_in_order(tmp_path):
    for n in (12, 3, 7):
        (tmp_path / f"shot_{n:04d}.exr").write_bytes(b"")
    (tmp_path / "shot_12.exr").write_bytes(b"")                        # not four digits: not a frame
    (tmp_path / "other_0001.exr").write_bytes(b"")
    assert sequence_files(str(tmp_path / "shot_####.exr")) == [(n, tmp_path / f"shot_{n:04d}.exr") for n in (3, 7, 12)]
    (tmp_path / "005").mkdir()
    (tmp_path / "005" / "s00.exr").write_bytes(b"")
    assert sequence_files(str(tmp_path / "###" / "s00.exr")) == [(5, tmp_path / "005" / "s00.exr")]
    assert output_path("out/f_####.exr", 7) == output_path("out/f_####.exr", 7) and \
        str(output_path("out/f_####.exr", 7)) == "out/f_0007.exr"
    with pytest.raises(TrainError, match="expected one run of #"):
        sequence_files(str(tmp_path / "a_##_##.exr"))
    with pytest.raises(TrainError, match="no file matches"):
        sequence_files(str(tmp_path / "none_####.exr"))


def test_outputs_that_would_overwrite_an_input_are_refused_in_one_line(tmp_path):
    for n in range(2):
        write_rgb_exr(tmp_path / f"f_{n:02d}.exr", np.ones((8, 8, 3), np.float32))
    proc = cli("denoise", "--sequence", tmp_path / "f_##.exr", "--out", tmp_path / "f_##.exr", check=False)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "is one of the inputs" in proc.stderr


@pytest.mark.slow
def test_a_rendered_orbit_takes_history_and_plain_exrs_are_denoised_alone(tmp_path):
    xml = tmp_path / "s.xml"
    xml.write_text(ORBIT_SCENE.format(second=""))
    proc = cli("render-scene", xml, "--frames", "3", "--move", "orbit:10", "--store", tmp_path / "st", "--config",
               TINY, "dataset.stacks=1")
    frames = str(tmp_path / "st" / "scenes" / "ext_s" / "###" / "s00.exr")
    assert f"denoise --sequence '{frames}' --spp 4" in proc.stdout          # what render-scene says to run
    proc = cli("denoise", "--sequence", frames, "--out", tmp_path / "out" / "f_###.exr", "--method", "oidn_prefilter",
               "--spp", "4", "--quiet")
    # the frames after are read (eval.temporal_ahead): the filter on both sides, so the first frame has a history too
    assert "history on 3 of 3 frames" in proc.stdout and "filter on both sides" in proc.stdout, proc.stdout
    records = [read_header(tmp_path / "out" / f"f_{n:03d}.exr") for n in range(3)]
    assert all(r["temporal"]["history_fraction"] > 0.5 and r["temporal"]["both_sides"] for r in records)
    proc = cli("denoise", "--sequence", frames, "--out", tmp_path / "causal" / "f_###.exr", "--method",
               "oidn_prefilter", "--spp", "4", "--ahead", "0", "--quiet")
    assert "history on 2 of 3 frames" in proc.stdout and "both sides" not in proc.stdout, proc.stdout
    assert read_header(tmp_path / "causal" / "f_000.exr")["temporal"]["history_fraction"] is None
    # weight 1, a window of 1 and none ahead keep no history: each frame is OIDN's final-frame output alone, as
    # denoise --exr writes it
    cli("denoise", "--sequence", frames, "--out", tmp_path / "one" / "f_###.exr", "--method", "oidn_prefilter",
        "--spp", "4", "--temporal-weight", "1", "--temporal-window", "1", "--ahead", "0", "--quiet")
    single = tmp_path / "single.exr"
    cli("denoise", "--exr", frames.replace("###", "001"), "--out", single, "--method", "oidn_prefilter", "--quiet")
    colour = lambda path: read_layers(path)["color"]                  # noqa: E731
    assert np.array_equal(colour(tmp_path / "one" / "f_001.exr"), colour(single))
    assert not np.array_equal(colour(tmp_path / "out" / "f_001.exr"), colour(single))
    # the diffuse light averaged over 3 frames: frame 0 as before, the later frames denoised from more samples
    proc = cli("denoise", "--sequence", frames, "--out", tmp_path / "avg" / "f_###.exr", "--method", "oidn_prefilter",
               "--spp", "4", "--temporal-weight", "1", "--temporal-window", "3", "--ahead", "0", "--quiet")
    assert "diffuse light averaged over up to 3 frames and 0 after" in proc.stdout, proc.stdout
    assert np.array_equal(colour(tmp_path / "avg" / "f_000.exr"), colour(tmp_path / "one" / "f_000.exr"))
    assert not np.array_equal(colour(tmp_path / "avg" / "f_002.exr"), colour(tmp_path / "one" / "f_002.exr"))
    # and the frame after each: frame 0 averages frame 1 too, the last frame has none after it
    proc = cli("denoise", "--sequence", frames, "--out", tmp_path / "ahead" / "f_###.exr", "--method",
               "oidn_prefilter", "--spp", "4", "--temporal-weight", "1", "--temporal-window", "3", "--ahead", "1",
               "--quiet")
    assert "diffuse light averaged over up to 3 frames and 1 after" in proc.stdout, proc.stdout
    assert not np.array_equal(colour(tmp_path / "ahead" / "f_000.exr"), colour(tmp_path / "one" / "f_000.exr"))
    assert np.array_equal(colour(tmp_path / "ahead" / "f_002.exr"), colour(tmp_path / "avg" / "f_002.exr"))
    # the outputs keep the input's camera: a compositor (or another pass) can still reproject them
    for result in (tmp_path / "out" / "f_002.exr", single):
        source = frames.replace("###", "002" if result.name == "f_002.exr" else "001")
        kept, given = exr_matrices(read_camera(result)), exr_matrices(read_camera(source))
        for name in kept:       # read back from float32, rebuilt in float64, written as float32: a few ulps
            np.testing.assert_allclose(kept[name], given[name], rtol=1e-5, atol=1e-6)
    # the same frames as plain R, G, B files: no camera, no depth, so frame by frame, said once
    plain = tmp_path / "plain"
    plain.mkdir()
    for n in range(3):
        layers = read_layers(frames.replace("###", f"{n:03d}"))
        write_rgb_exr(plain / f"p_{n}.exr", layers["color"])
    proc = cli("denoise", "--sequence", plain / "p_#.exr", "--out", tmp_path / "po" / "p_#.exr", "--method",
               "oidn_prefilter", "--spp", "4", "--quiet", check=False)
    assert proc.returncode == 2 and "prefilters albedo and normal" in proc.stderr   # OIDN's mode needs aux
    proc = cli("denoise", "--sequence", plain / "p_#.exr", "--out", tmp_path / "po" / "p_#.exr", "--spp", "4",
               "--temporal-window", "3", "--quiet")
    assert proc.stdout.count("no motion for that frame") == 1 and "history on 0 of 3 frames" in proc.stdout
    assert "input not averaged (no frame has diffuse light layers)" in proc.stdout, proc.stdout
    shutil.rmtree(plain)


def cropped_exr(path, camera, size: tuple[int, int]) -> None:
    """An EXR of colour and depth whose pixels (the data window) are ``size`` (H, W) and whose display window and
    camera attributes are ``camera``'s: a crop, as a renderer writes a region of its frame."""
    h, w = size
    channels = {c: np.full((h, w), 0.5, np.float32) for c in "RGB"}
    channels["depth.Z"] = np.full((h, w), 3.0, np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **exr_matrices(camera),
              "displayWindow": (np.array([0, 0], np.int32), np.array([camera.width - 1, camera.height - 1], np.int32))}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def test_black_frames_are_written_black_and_said_so(tmp_path):
    for n in range(2):
        with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                          {c: np.zeros((6, 8), np.float32) for c in "RGB"}) as f:
            f.write(str(tmp_path / f"k_{n}.exr"))
    proc = cli("denoise", "--sequence", tmp_path / "k_#.exr", "--out", tmp_path / "o" / "k_#.exr", "--spp", "4",
               "--quiet")
    assert "a black input frame is written black" in proc.stdout and "layers:  alone" not in proc.stdout, proc.stdout
    assert not np.any(read_layers(tmp_path / "o" / "k_1.exr")["color"])


def test_a_display_window_other_than_the_pixels_is_denoised_alone_in_one_line(tmp_path):
    cam = motion.Camera(look_at([0, 0, -3], [0, 0, 0], [0, 1, 0]), 40.0, 32, 24)
    for n in range(2):
        cropped_exr(tmp_path / f"c_{n}.exr", cam, (12, 16))
    assert frame_view(tmp_path / "c_0.exr", read_layers(tmp_path / "c_0.exr")) == \
        (None, "display window 32x24 differs from the pixels' 16x12, and no Vector pass")
    proc = cli("denoise", "--sequence", tmp_path / "c_#.exr", "--out", tmp_path / "o" / "c_#.exr", "--spp", "4",
               "--device", "cpu", "--quiet")
    assert proc.stdout.count("note: ") == 1 and "display window 32x24 differs from the pixels' 16x12" in proc.stdout
    assert "history on 0 of 2 frames" in proc.stdout, proc.stdout
    assert read_layers(tmp_path / "o" / "c_1.exr")["color"].shape == (12, 16, 3)


def blender_frame(path, colour, albedo, vector, light: bool = False) -> None:
    """A Cycles multilayer EXR: the Denoising Data passes and the Vector pass under the view layer 'ViewLayer'; with
    ``light``, Cycles' light passes too, every bit of light diffuse and direct (DiffDir = the colour, DiffCol = 1)."""
    channels = {}
    zero, one = np.zeros(colour.shape, np.float32), np.ones(colour.shape, np.float32)
    passes = (("DiffDir", colour), ("DiffInd", zero), ("DiffCol", one), ("GlossDir", zero), ("GlossInd", zero),
              ("GlossCol", one)) if light else ()
    for layer, image, suffixes in (("Noisy Image", colour, "RGB"), ("Denoising Albedo", albedo, "RGB"),
                                   ("Vector", vector, "XYZW"), *((n, im, "RGB") for n, im in passes)):
        for k, s in enumerate(suffixes):
            channels[f"ViewLayer.{layer}.{s}"] = np.ascontiguousarray(image[..., k], np.float32)
    normal = np.zeros(colour.shape, np.float32)
    normal[..., 2] = 1.0
    for k, s in enumerate("XYZ"):
        channels[f"ViewLayer.Denoising Normal.{s}"] = normal[..., k].copy()
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(path))


@pytest.mark.slow
def test_a_blender_sequence_follows_its_vector_pass(tmp_path):
    """Three frames of a picture that moves right by 2 pixels and down by 1 per frame, as Blender writes them
    (Denoising Data and Vector passes, no camera): frame t's history is the previous output moved by (2, 1),
    valid where that pixel was on screen."""
    h, w, n = 24, 32, 3
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:h + n, 0:w + 2 * n]
    base = np.stack([(x % 9 < 4) * 0.8 + 0.1, (y % 7 < 3) * 0.6 + 0.2, 0.3 + 0.02 * x], -1).astype(np.float32)
    # Cycles' convention (y up): X, Y = previous position - this one = (-2, +1); Z, W = this one - next = (-2, +1)
    vector = np.broadcast_to(np.array([-2, 1, -2, 1], np.float32), (h, w, 4))
    for t in range(n):
        clean = base[n - t:n - t + h, 2 * (n - t):2 * (n - t) + w]        # frame t sees base shifted by (2t, t)
        noisy = clean * rng.gamma(4.0, 0.25, clean.shape).astype(np.float32)
        blender_frame(tmp_path / f"b_{t:02d}.exr", noisy, clean, vector)
        blender_frame(tmp_path / f"l_{t:02d}.exr", noisy, clean, vector, light=True)
    passes: dict = {}
    buffers = read_layers(tmp_path / "b_00.exr", passes=passes)
    assert passes["Vector"].shape == (h, w, 4) and frame_view(tmp_path / "b_00.exr", buffers)[0] is None
    assert frame_view(tmp_path / "b_00.exr", buffers, passes["Vector"])[0].motion is not None
    run = ("denoise", "--sequence", tmp_path / "b_##.exr", "--method", "oidn_prefilter", "--spp", "4", "--quiet")
    proc = cli(*run, "--out", tmp_path / "seq" / "o_##.exr", "--temporal-weight", "0.5", "--ahead", "0")
    assert "history on 2 of 3 frames" in proc.stdout and "note:" not in proc.stdout, proc.stdout
    cli(*run, "--out", tmp_path / "alone" / "o_##.exr", "--temporal-weight", "1")
    colour = lambda d, t: read_layers(tmp_path / d / f"o_{t:02d}.exr")["color"]     # noqa: E731
    valid = np.zeros((h, w), bool)
    valid[1:, 2:] = True
    for t in (1, 2):
        assert read_header(tmp_path / "seq" / f"o_{t:02d}.exr")["temporal"]["history_fraction"] == valid.mean()
        history = np.zeros((h, w, 3), np.float32)
        history[1:, 2:] = colour("seq", t - 1)[:-1, :-2]                   # the previous output, moved by (2, 1)
        expected = temporal.blend_history(colour("alone", t), history, valid, 0.5)
        # float32 outputs, and a shift by whole pixels reads each pixel alone (motion.TAP_EPS): the same arithmetic
        np.testing.assert_allclose(colour("seq", t), expected, rtol=1e-6, atol=0)
        assert not np.allclose(colour("seq", t), colour("alone", t), rtol=1e-2)
    # on both sides (the frames after read): frame 1's history is the mean of frame 0's output moved by (2, 1) and
    # frame 2's moved back by (-2, -1), each where on screen; the last frame has none after it, so it is the causal
    # filter's own
    proc = cli(*run, "--out", tmp_path / "both" / "o_##.exr", "--temporal-weight", "0.5")
    assert "history on 3 of 3 frames" in proc.stdout, proc.stdout
    before, after = np.zeros((h, w, 3), np.float32), np.zeros((h, w, 3), np.float32)
    before[1:, 2:], after[:-1, :-2] = colour("alone", 0)[:-1, :-2], colour("alone", 2)[1:, 2:]
    expected = temporal.blend_sides(colour("alone", 1), [(before, valid), (after, valid[::-1, ::-1])], 0.5)
    np.testing.assert_allclose(colour("both", 1), expected, rtol=1e-6, atol=0)
    np.testing.assert_array_equal(colour("both", 2), colour("seq", 2))
    # ours on Blender's passes: no variance, light components or material layers, so the model's base alone, said
    proc = cli("denoise", "--sequence", tmp_path / "b_##.exr", "--spp", "4", "--quiet", "--device", "cpu",
               "--out", tmp_path / "ours" / "o_##.exr")
    assert "history on 3 of 3 frames" in proc.stdout and "the model's base, OIDN, alone" in proc.stdout, proc.stdout
    # with the light passes the model reads the light components, and the diffuse light is averaged over the frame
    # before and, followed forward along the vectors, the frames after: per frame 1 + the share of its pixels
    # still on screen one frame away (30/32 * 23/24) or two (28/32 * 22/24), (2.70 + 2.80 + 2.70) / 3
    proc = cli("denoise", "--sequence", tmp_path / "l_##.exr", "--spp", "4", "--quiet", "--device", "cpu",
               "--out", tmp_path / "light" / "o_##.exr")
    assert "diffuse light ÷ albedo averaged over up to 8 frames and 7 after (2.7 per pixel)" in proc.stdout, proc.stdout
    assert "base, OIDN, alone" not in proc.stdout, proc.stdout
