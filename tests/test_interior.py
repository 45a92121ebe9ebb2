"""Furnished interiors and product shots (scene.interior_probability, scene.product_probability): the kinds
are drawn only when asked for (configs without them draw the same open-set scenes), descriptions are
deterministic, the camera stands in free space inside the room, bulbs sit inside their shades, cove and
recessed lights are hidden from the camera, and every scene builds and renders in Mitsuba."""
from __future__ import annotations

import dataclasses
import gc
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.pipeline.config import SceneConfig, load_config
from mcdenoise.render.geometry import mesh_arrays
from mcdenoise.render.room import label_at, wall_segments
from mcdenoise.render.scene import random_scene, scene_kind

ROOT = Path(__file__).resolve().parents[1]
INTERIOR = dataclasses.replace(SceneConfig(), interior_probability=1.0)
PRODUCT = dataclasses.replace(SceneConfig(), product_probability=1.0)
# sha256 of the JSON of scenes 0-23 (2 frames) of each shipped config that draws no interiors or products: the
# kinds draw from streams of their own, so these open-set scenes do not depend on them.
BEFORE = {"default": "bffee243c16783bc1bd8cec5f8823ed6840f6b765080ac979ba62d73bc32cd8b",
          "ship": "1d1202451f958cfa8ff5fb952fc2f07f24209786722e8487cfd00b7f933c417c",
          "tiny": "4a0d5146443d4422bc71ddaa809ae120bd4c341dfe6b86b58fdfea479199cca9",
          "paper": "b3d535c4adeefd144b1233a27bc5e1180e89c3f45bc62417a6d13a6dbad2d369"}


def test_the_yaw_of_furniture_is_the_rotation_of_cameras_and_meshes():
    """A placed item's points turn (furniture._turn) as its meshes do (geometry.transform_matrix) and as a
    camera turns about +y (camera.rotation)."""
    from mcdenoise.render.camera import rotation
    from mcdenoise.render.furniture import _turn
    from mcdenoise.render.geometry import transform_matrix

    rng = np.random.default_rng(5)
    for yaw in (0.0, 90.0, -37.5, 180.0, 271.3):
        v = rng.normal(size=3)
        turned = _turn(v, yaw)
        np.testing.assert_allclose(turned, rotation((0, 1, 0), np.radians(yaw)) @ v, atol=1e-12)
        np.testing.assert_allclose(turned, transform_matrix({"rotation_deg": [0, yaw, 0]})[:3, :3] @ v, atol=1e-12)
    np.testing.assert_allclose(_turn([0, 0, 1], 30.0), [0.5, 0, np.cos(np.radians(30))], atol=1e-15)


def _digest(cfg, seed: int, count: int = 24) -> str:
    h = hashlib.sha256()
    for i in range(count):
        h.update(json.dumps(random_scene(cfg, seed, i, 2), sort_keys=True).encode())
    return h.hexdigest()


@pytest.mark.parametrize("name", sorted(BEFORE))
def test_shipped_configs_draw_the_scenes_they_drew_before(name):
    cfg = load_config(ROOT / "configs" / f"{name}.yaml")
    assert _digest(cfg.scene, cfg.seed) == BEFORE[name]
    zero = dataclasses.replace(cfg.scene, interior_probability=0.0, product_probability=0.0)
    assert _digest(zero, cfg.seed) == BEFORE[name]


def test_kinds_are_drawn_with_their_probabilities():
    assert all(random_scene(INTERIOR, 0, i, 1)["kind"] == "interior" for i in range(8))
    assert all(random_scene(PRODUCT, 0, i, 1)["kind"] == "product" for i in range(8))
    both = dataclasses.replace(SceneConfig(), interior_probability=1.0, product_probability=1.0)
    assert {scene_kind(both, 0, i) for i in range(20)} == {"interior"}      # interiors are drawn first
    mix = dataclasses.replace(SceneConfig(), interior_probability=0.4, product_probability=0.5)
    kinds = [scene_kind(mix, 0, i) for i in range(300)]
    assert 0.3 < kinds.count("interior") / 300 < 0.5
    assert 0.22 < kinds.count("product") / 300 < 0.38          # half of the remaining 60 %
    for i, kind in enumerate(kinds[:12]):                      # today's scenes stay as they were
        if kind == "objects":
            assert random_scene(mix, 0, i, 1) == random_scene(SceneConfig(), 0, i, 1)


@pytest.mark.parametrize("cfg", [INTERIOR, PRODUCT], ids=["interior", "product"])
def test_descriptions_are_deterministic_json(cfg):
    for index in range(6):
        a = random_scene(cfg, 3, index, 3)
        assert json.dumps(a, sort_keys=True) == json.dumps(random_scene(cfg, 3, index, 3), sort_keys=True)
        assert json.loads(json.dumps(a)) == a and len(a["camera"]["frames"]) == 3 and a["objects"]
    assert random_scene(cfg, 3, 0, 2) != random_scene(cfg, 4, 0, 2)


def _boxes(desc) -> list:
    """(name, lo, hi) of every object's triangles, as built."""
    out = []
    for obj in desc["objects"]:
        v = mesh_arrays(obj["shape"], obj["transform"])["positions"]
        out.append((obj["name"], v.min(0), v.max(0)))
    return out


def test_the_camera_stands_inside_the_room_clear_of_furniture():
    lightings = set()
    for index in range(16):
        desc = random_scene(INTERIOR, 0, index, 3)
        lightings.add(desc["lighting"])
        plan, boxes = desc["plan"], _boxes(desc)
        for pose in desc["camera"]["frames"]:
            o = np.asarray(pose["origin"])
            assert label_at(plan, o[0], o[2]) == 0 and 1.0 < o[1] < plan["height"] - 0.5
            inside = [name for name, lo, hi in boxes if np.all(o > lo - 0.05) and np.all(o < hi + 0.05)]
            assert not inside, (index, inside)
            view = np.subtract(pose["target"], pose["origin"])
            assert abs(view[1]) < np.linalg.norm(view[[0, 2]])     # looking across the room, not at floor or ceiling
    assert len(lightings) >= 4, lightings


def test_every_bulb_sits_inside_its_shade():
    bulbs = 0
    for index in range(30):
        desc = random_scene(INTERIOR, 1, index, 1)
        shades = {o["name"].rsplit(".", 1)[0]: o for o in desc["objects"] if o["name"].endswith(".shade")}
        for light in (li for li in desc["lights"] if li.get("role") == "bulb"):
            bulbs += 1
            c, r = np.asarray(light["center"]), light["radius"]
            # the shade object built: its cone's radius at the bulb's height bounds the bulb
            near = [o for o in shades.values() if np.allclose(o["transform"]["position"][::2], light["shade"]["axis"][::2])]
            v = mesh_arrays(near[0]["shape"], near[0]["transform"])["positions"]
            axis = np.asarray(light["shade"]["axis"])
            radial = np.hypot(v[:, 0] - axis[0], v[:, 2] - axis[2])
            lo, hi = v[:, 1].min(), v[:, 1].max()
            assert lo + r < c[1] < hi - r
            assert np.hypot(*(c - axis)[::2]) + r < radial[radial > 0.01].min()
    assert bulbs >= 10


def test_cove_lights_sit_behind_a_ledge_above_the_camera():
    coves = 0
    for index in range(40):
        desc = random_scene(INTERIOR, 2, index, 2)
        for light in (li for li in desc["lights"] if li.get("role") == "cove"):
            coves += 1
            eye = max(p["origin"][1] for p in desc["camera"]["frames"])
            ledge = [b for b in _boxes(desc) if b[0].startswith("cove")]
            c = np.asarray(light["center"])
            assert light["normal"] == [0.0, 1.0, 0.0] and light["hidden"]
            # some cove box lies under the emitter, wider than it, and the whole cove is above every eye
            assert any(lo[1] < c[1] and lo[0] <= c[0] - light["size"][0] / 2 and hi[0] >= c[0] + light["size"][0] / 2
                       and lo[2] <= c[2] - light["size"][1] / 2 and hi[2] >= c[2] + light["size"][1] / 2 and lo[1] > eye
                       for _, lo, hi in ledge)
    assert coves >= 3


def test_plans_have_walls_around_every_room():
    for index in range(12):
        plan = random_scene(INTERIOR, 0, index, 1)["plan"]
        segs = wall_segments(plan)
        rooms = {q["room"] for q in plan["rects"]}
        assert all(any(r in s["rooms"] and -1 in s["rooms"] for s in segs) for r in rooms)
        if 1 in rooms:   # the neighbour shares a wall (with a door) with the main room
            assert any(sorted(s["rooms"]) == [0, 1] and s["span"][1] - s["span"][0] >= 1.1 for s in segs)


def test_wall_segments_of_an_l_shaped_room():
    plan = {"height": 2.5, "rects": [{"x": [0, 4], "z": [0, 3], "room": 0}, {"x": [4, 6], "z": [0, 1.5], "room": 0},
                                     {"x": [-3, 0], "z": [1, 3], "room": 1}]}
    segs = wall_segments(plan)
    perimeter0 = sum(s["span"][1] - s["span"][0] for s in segs if 0 in s["rooms"])
    assert perimeter0 == pytest.approx(2 * (6 + 3))                   # an L's perimeter: its bounding box's
    shared = [s for s in segs if sorted(s["rooms"]) == [0, 1]]
    assert shared == [{"line": "x", "at": 0, "span": [1, 3], "rooms": [1, 0]}]
    assert not any(s["line"] == "x" and s["at"] == 4 and s["span"][0] < 1.5 for s in segs)   # no wall inside the L


def test_product_shots_are_close_and_tele():
    for index in range(10):
        desc = random_scene(PRODUCT, 0, index, 2)
        c = np.asarray(desc["cluster"]["center"])
        for pose in desc["camera"]["frames"]:
            assert 15 <= pose["fov"] <= 36 and np.linalg.norm(np.subtract(pose["origin"], c)) < 3.0
        products = [o for o in desc["objects"] if o["name"].startswith("product")]
        assert 1 <= len({o["name"].split(".")[0] for o in products}) <= 4
        assert all(li["type"] == "rectangle" for li in desc["lights"]) and desc["lights"]
        steps = np.linalg.norm(np.diff([p["origin"] for p in desc["camera"]["frames"]], axis=0), axis=1)
        assert 0 < steps.sum() < 0.12 * np.linalg.norm(np.subtract(desc["camera"]["frames"][0]["origin"], c))


# --------------------------------------------------------------------------------------------
# Rendered


@pytest.fixture(scope="module")
def mi():
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba

    return import_mitsuba("llvm_ad_rgb")


def _render(mi, desc, frame=0, spp=4, max_depth=8, size=32):
    from mcdenoise.render.scene import build_scene, build_sensor

    scene = build_scene(mi, desc)
    img = np.asarray(mi.render(scene, sensor=build_sensor(mi, desc, frame, size, size),
                               integrator=mi.load_dict({"type": "path", "max_depth": max_depth}), spp=spp))
    del scene
    gc.collect()
    return img


@pytest.mark.slow
@pytest.mark.parametrize("cfg", [INTERIOR, PRODUCT], ids=["interior", "product"])
def test_scenes_build_and_render_lit(mi, cfg):
    means = []
    for index in range(6):
        desc = random_scene(cfg, 5, index, 2)
        img = _render(mi, desc, frame=index % 2, spp=4)
        assert img.shape == (32, 32, 3) and np.isfinite(img).all()
        means.append(float(img.mean()))
    assert all(0.002 < m < 5.0 for m in means), means


@pytest.mark.slow
def test_hidden_lights_are_not_seen_by_the_camera(mi):
    """Cove and recessed lights alone, seen directly (paths of length 1): black from every frame; lit (all
    bounces): not black."""
    found = 0
    for index in range(40):
        desc = random_scene(INTERIOR, 6, index, 2)
        hidden = [li for li in desc["lights"] if li.get("hidden")]
        if not hidden or found >= 3:
            continue
        found += 1
        alone = dict(desc, lights=hidden, environment=None)
        for frame in (0, 1):
            assert _render(mi, alone, frame, spp=4, max_depth=1, size=48).max() == 0
        assert _render(mi, alone, 0, spp=8).mean() > 1e-3
    assert found == 3


def test_surface_textures_in_range_and_deterministic():
    from mcdenoise.render.textures import SURFACE_KINDS, make_texture, surface_texture_params

    rng = np.random.default_rng(0)
    for kind in SURFACE_KINDS:
        p = surface_texture_params(rng, kind, [[0.1, 0.05, 0.02], [0.5, 0.3, 0.2], [0.8, 0.8, 0.8]], 4, 1.0, size=64)
        a = make_texture(p)
        assert a.shape == (64, 64, 3) and np.array_equal(a, make_texture(p)) and 0 <= a.min() and a.max() <= 1
        assert a.std() > 0.005, kind
    with pytest.raises(ValueError, match="wood"):
        surface_texture_params(rng, "marble", [[0, 0, 0]], 4, 1.0)
