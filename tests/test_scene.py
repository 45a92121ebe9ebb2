"""Scene randomizer: determinism, JSON descriptions, building and rendering every material family and
stress preset, user meshes, the camera move and the procedural textures."""
from __future__ import annotations

import dataclasses
import gc
import json

import numpy as np
import pytest

from mcdenoise.pipeline.config import SceneConfig
from mcdenoise.render import camera as cam, lights as lt
from mcdenoise.render.materials import FAMILIES
from mcdenoise.render.scene import STRESS_PRESETS, random_scene, stress_scene
from mcdenoise.render.textures import KINDS, make_texture, random_texture_params


@pytest.fixture(scope="module")
def mi():
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba

    return import_mitsuba("llvm_ad_rgb")


def _sensor(mi, desc, frame, size=32):
    # Private equivalent of render.buffers.make_sensor, so these tests do not depend on it.
    pose = desc["camera"]["frames"][frame]
    return mi.load_dict({"type": "perspective", "fov": pose["fov"], "to_world": cam.to_world(mi, pose),
                         "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}}})


def _render(mi, desc, frame=0, spp=4):
    from mcdenoise.render.scene import build_scene

    scene = build_scene(mi, desc)
    img = np.asarray(mi.render(scene, sensor=_sensor(mi, desc, frame), integrator=mi.load_dict({"type": "path"}),
                               spp=spp))
    del scene
    gc.collect()
    return img


def test_deterministic_and_distinct():
    cfg = SceneConfig()
    a, b = random_scene(cfg, 7, 3, 4), random_scene(cfg, 7, 3, 4)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    assert json.dumps(a, sort_keys=True) != json.dumps(random_scene(cfg, 7, 4, 4), sort_keys=True)
    assert json.dumps(a, sort_keys=True) != json.dumps(random_scene(cfg, 8, 3, 4), sort_keys=True)


def test_json_round_trip_and_counts():
    cfg = SceneConfig()
    for index in range(10):
        desc = random_scene(cfg, 0, index, 3)
        assert json.loads(json.dumps(desc)) == desc
        assert desc["preset"] is None and desc["ground"] is not None
        assert cfg.objects[0] <= len(desc["objects"]) <= cfg.objects[1]
        assert cfg.area_lights[0] <= sum(light["type"] in ("rectangle", "sphere") for light in desc["lights"])
        for obj in desc["objects"]:
            assert obj["transform"]["position"][1] >= 0  # lowest point on or above the ground
    for name in STRESS_PRESETS:
        desc = stress_scene(name, 0, 2)
        assert json.loads(json.dumps(desc)) == desc and desc["preset"] == name


def test_unknown_preset():
    with pytest.raises(ValueError, match="caustics"):
        stress_scene("nope", 0, 2)


def test_camera_moves_smoothly():
    cfg = SceneConfig()
    for frames in (1, 2, 8):
        desc = random_scene(cfg, 1, 0, frames)
        assert len(desc["camera"]["frames"]) == frames
    poses = desc["camera"]["frames"]
    origins = np.array([p["origin"] for p in poses])
    steps = np.linalg.norm(np.diff(origins, axis=0), axis=1)
    center = np.asarray(desc["cluster"]["center"])
    dist = np.linalg.norm(origins[0] - center)
    assert np.all(steps > 1e-4)                       # the camera does move every frame
    assert steps.sum() < cfg.camera_move * dist * 2   # ... by a small amount in total
    assert steps.max() < 2.5 * steps.min() + 1e-6     # ... in even steps (no jumps)
    assert all(o[1] > 0 for o in origins)
    for p in poses:  # the cluster centre stays in front of the camera, within the field of view
        fwd = np.subtract(p["target"], p["origin"])
        to_c = center - np.asarray(p["origin"])
        cos = fwd @ to_c / np.linalg.norm(fwd) / np.linalg.norm(to_c)
        assert np.degrees(np.arccos(cos)) < p["fov"] / 2


def test_textures_in_range_and_deterministic():
    rng = np.random.default_rng(0)
    for kind in KINDS:
        p = random_texture_params(rng, size=64)
        p["kind"] = kind
        a, b = make_texture(p), make_texture(p)
        assert a.shape == (64, 64, 3) and a.dtype == np.float32
        assert np.array_equal(a, b) and a.min() >= 0 and a.max() <= 1 and a.std() > 0


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_every_material_family_renders(mi, family):
    cfg = dataclasses.replace(SceneConfig(), materials={family: 1.0}, objects=[2, 2], texture_probability=0.5)
    desc = random_scene(cfg, 0, 11, 1)
    assert {o["material"]["family"] for o in desc["objects"]} == {family}
    img = _render(mi, desc)
    assert img.shape == (32, 32, 3) and np.isfinite(img).all() and img.mean() > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", STRESS_PRESETS)
def test_every_stress_preset_renders(mi, name):
    img = _render(mi, stress_scene(name, 0, 2), frame=1)
    assert np.isfinite(img).all() and img.mean() > 0


@pytest.mark.slow
def test_user_mesh_folder(mi, tmp_path):
    import trimesh

    trimesh.creation.annulus(r_min=0.2, r_max=0.5, height=0.3).export(tmp_path / "ring.obj")
    (tmp_path / "notes.txt").write_text("not a mesh")
    cfg = dataclasses.replace(SceneConfig(), mesh_dirs=[str(tmp_path)], mesh_probability=1.0, objects=[2, 2])
    desc = random_scene(cfg, 0, 0, 1)
    assert [o["shape"] for o in desc["objects"]] == [{"kind": "file", "path": str(tmp_path / "ring.obj")}] * 2
    img = _render(mi, desc)
    assert np.isfinite(img).all() and img.mean() > 0


@pytest.mark.slow
def test_random_scenes_are_lit(mi):
    means = [float(_render(mi, random_scene(SceneConfig(), 3, i, 1), spp=4).mean()) for i in range(3)]
    assert all(np.isfinite(means)) and all(0.003 < m < 5.0 for m in means), means


@pytest.mark.slow
def test_build_sensor(mi):
    from mcdenoise.render.scene import build_sensor

    desc = random_scene(SceneConfig(), 0, 0, 2)
    sensor = build_sensor(mi, desc, 1, 48, 32)
    assert tuple(int(v) for v in sensor.film().size()) == (48, 32)
    with pytest.raises(IndexError):
        build_sensor(mi, desc, 2, 48, 32)


def _roughness(material):
    return material.get("alpha", material.get("roughness", 1.0)) if material["family"] != "diffuse" else 1.0


def test_polished_surfaces_only_when_asked():
    """scene.polished_probability: at 1 every ground and wall is a smooth coat (sharp reflections), at 0 the
    ground is never smoother than the matte-ish palette allows."""
    polished = dataclasses.replace(SceneConfig(), polished_probability=1.0)
    for index in range(12):
        desc = random_scene(polished, 0, index, 1)
        for surface in [desc["ground"], *desc["walls"]]:
            assert surface["material"]["family"] in ("roughplastic", "principled")
            assert _roughness(surface["material"]) <= 0.15
    plain = [random_scene(SceneConfig(), 0, i, 1) for i in range(12)]
    assert all(d["ground"]["material"]["family"] == "diffuse" or _roughness(d["ground"]["material"]) >= 0.03
               for d in plain)


@pytest.mark.slow
def test_a_polished_ground_renders(mi):
    desc = random_scene(dataclasses.replace(SceneConfig(), polished_probability=1.0), 0, 5, 1)
    img = _render(mi, desc)
    assert np.isfinite(img).all() and img.mean() > 0


def _inside(point, rect) -> bool:
    """Whether ``point`` (on the rectangle's plane) lies within the rectangle."""
    n, up = np.asarray(rect["normal"], float), np.asarray(rect["up"], float)
    across = np.cross(up, n)
    d = np.asarray(point, float) - np.asarray(rect["center"], float)
    return abs(d @ across) < rect["size"][0] / 2 and abs(d @ up) < rect["size"][1] / 2


def test_a_wall_with_a_window_covers_the_wall_but_the_window():
    from mcdenoise.render.layout import wall_with_window

    material = {"family": "diffuse", "reflectance": [0.5, 0.5, 0.5]}
    pieces = wall_with_window([3.0, 0.0, 1.0], [-1, 0, 0], 6.0, 2.5, (-1.0, 0.5, 0.8, 1.9), material)
    area = sum(p["size"][0] * p["size"][1] for p in pieces)
    assert area == pytest.approx(6.0 * 2.5 - 1.5 * 1.1)
    across = np.cross([0, 1, 0], [-1, 0, 0])
    wall_point = lambda u, v: np.array([3.0, v, 1.0]) + across * u  # noqa: E731
    assert not any(_inside(wall_point(-0.25, 1.35), p) for p in pieces)          # the window's centre: open
    for u, v in [(-2.5, 1.0), (2.5, 2.4), (0.0, 0.4), (0.0, 2.2)]:                 # beside, below and above it
        assert sum(_inside(wall_point(u, v), p) for p in pieces) == 1
    # a window reaching the floor leaves no zero-height piece below it
    assert len(wall_with_window([0, 0, 0], [0, 0, 1], 4.0, 2.0, (-1.0, 1.0, 0.0, 1.5), material)) == 3


def test_enclosed_rooms_only_when_asked():
    """scene.enclosed_probability: at 1 every scene is a closed room around its camera path, lit by a sky
    through 1-2 windows, with the same objects and camera as at 0 (the room draws from its own stream)."""
    closed = dataclasses.replace(SceneConfig(), enclosed_probability=1.0)
    no_light_inside = 0
    for index in range(10):
        desc, plain = random_scene(closed, 0, index, 2), random_scene(SceneConfig(), 0, index, 2)
        assert desc["objects"] == plain["objects"] and desc["camera"] == plain["camera"]
        assert desc["environment"]["type"] == "sky"
        no_light_inside += not desc["lights"]
        sides = [w for w in desc["walls"] if w["normal"][1] == 0]
        height = max(w["center"][1] + w["size"][1] / 2 for w in sides)
        ceiling = [w for w in desc["walls"] if w["normal"] == [0.0, -1.0, 0.0]]
        assert len(ceiling) == 1 and ceiling[0]["center"][1] == pytest.approx(height, abs=1e-3)   # 4 decimals
        half = desc["ground"]["size"][0] / 2
        for pose in desc["camera"]["frames"]:
            offset = np.subtract(pose["origin"], desc["ground"]["center"])
            assert max(abs(offset[0]), abs(offset[2])) < half and 0 < pose["origin"][1] < height
        openings = sum(1 for w in sides if w["size"][1] < height - 1e-6)
        assert openings >= 1   # a window: wall pieces below or above it are lower than the room
    assert 0 < no_light_inside < 10
    plain = [random_scene(SceneConfig(), 0, i, 1) for i in range(10)]
    assert not any(w["size"][1] < max(v["center"][1] + v["size"][1] / 2 for v in d["walls"] if v["normal"][1] == 0) - 1e-6
                   for d in plain for w in d["walls"] if w["normal"][1] == 0)


@pytest.mark.slow
def test_daylight_reaches_a_closed_room_through_its_window(mi):
    closed = dataclasses.replace(SceneConfig(), enclosed_probability=1.0)
    desc = next(d for d in (random_scene(closed, 0, i, 1) for i in range(20)) if not d["lights"])
    img = _render(mi, desc, spp=16)
    assert np.isfinite(img).all() and img.mean() > 0
    dark = dict(desc, environment={**desc["environment"], "scale": 0.0, "irradiance": 0.0})
    assert _render(mi, dark, spp=4).max() == 0     # the sky is the only light


def test_delta_suns_only_when_asked():
    """scene.sun_delta_probability: at 1 every sky's sun is a directional light and nothing else of the scene
    changes (its own stream); at 0 no scene has one (the scenes made before the key)."""
    delta = dataclasses.replace(SceneConfig(), sun_delta_probability=1.0, environment_probability=1.0)
    plain_cfg = dataclasses.replace(SceneConfig(), environment_probability=1.0)
    suns = 0
    for index in range(12):
        desc, plain = random_scene(delta, 0, index, 1), random_scene(plain_cfg, 0, index, 1)
        env, plain_env = desc["environment"], plain["environment"]
        assert {k: v for k, v in desc.items() if k != "environment"} == {k: v for k, v in plain.items() if k != "environment"}
        assert not lt.is_delta_sun(plain_env)
        if plain_env.get("sun"):
            suns += 1
            assert lt.is_delta_sun(env) and {**env["sun"], "delta": False} == {**plain_env["sun"], "delta": False}
        else:
            assert env == plain_env
    assert suns >= 3


def test_a_delta_sun_gives_the_irradiance_its_blob_gave():
    """The directional light carries what the sky map's sun blob carried: the map without the blob plus
    the directional irradiance equals the map with it, at normal incidence toward the sun."""
    env = next(e for e in (lt.random_environment(np.random.default_rng(seed), 5.0) for seed in range(50)) if e.get("sun"))
    h, w = lt.SKY_SIZE
    blob = lt.sky_bitmap(env).astype(np.float64) - lt.sky_bitmap({**env, "sun": {**env["sun"], "delta": True}})
    theta, phi = (np.arange(h) + 0.5) / h * np.pi, (np.arange(w) + 0.5) / w * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1)
    cos = np.clip(d @ lt.sun_direction(env["sun"]), 0, None)
    dA = np.sin(th) * (np.pi / h) * (2 * np.pi / w)
    from_blob = env["scale"] * np.einsum("hwc,hw->c", blob, cos * dA)
    sun = lt.sun_dict(env)
    np.testing.assert_allclose(sun["irradiance"]["value"], from_blob, rtol=1e-4)
    assert sun["type"] == "directional" and np.dot(sun["direction"], lt.sun_direction(env["sun"])) == pytest.approx(-1)


@pytest.mark.slow
def test_a_delta_sun_lights_the_ground_as_its_blob_did(mi):
    """Rendered: the ground under the delta sun is as bright as under the blob (Mitsuba's frame and ours
    agree on which way is down) and the render has no other light."""
    cfg = dataclasses.replace(SceneConfig(), environment_probability=1.0, sun_delta_probability=1.0)
    desc = next(d for d in (random_scene(cfg, 5, i, 1) for i in range(40))
                if lt.is_delta_sun(d["environment"] or {}) and d["environment"]["sun"]["elevation_deg"] > 30)
    bare = dict(desc, objects=[], walls=[], lights=[])
    blob = dict(bare, environment={**bare["environment"], "sun": {**bare["environment"]["sun"], "delta": False}})
    a, b = _render(mi, bare, spp=64), _render(mi, blob, spp=64)
    assert np.isfinite(a).all() and np.median(a) == pytest.approx(np.median(b), rel=0.1)
    no_sun = dict(bare, environment={**bare["environment"], "sun": None})
    assert np.median(_render(mi, no_sun, spp=16)) < 0.8 * np.median(a)
