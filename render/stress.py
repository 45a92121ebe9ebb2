"""Stress presets: named, hand-built extreme scenes in the same description format as the random
ones (``render.scene``), rendered into the store's split ``stress`` (``dataset.stress``) to see where
a denoiser breaks.

Each preset is deterministic in (name, seed); the seed only varies the free details (object
shapes, colours, the camera path), never what makes the case extreme.
"""
from __future__ import annotations

import zlib

import numpy as np

from pipeline.config import SceneConfig
from render import camera as cam, lights as lt
from render.layout import ground, place_objects, rect, room_walls

STRESS_PRESETS: tuple[str, ...] = ("tiny_bright_light", "caustics", "dark_room_gap", "mirrors",
                                   "emitter_fills_view", "empty_environment", "degenerate_geometry")

GREY = {"family": "diffuse", "reflectance": [0.5, 0.5, 0.5]}
WHITE = {"family": "diffuse", "reflectance": [0.75, 0.75, 0.75]}
BLACK = {"family": "diffuse", "reflectance": [0.0, 0.0, 0.0]}
GLASS = {"family": "dielectric", "int_ior": 1.5, "ext_ior": 1.000277}
MIRROR = {"family": "conductor", "material": "Ag"}


def _obj(name, shape, material, position, scale, rotation=(0, 0, 0), two_sided=False, rest=True) -> dict:
    return {"name": name, "shape": shape, "material": material, "two_sided": two_sided,
            "transform": {"scale": scale, "rotation_deg": list(rotation), "position": list(position),
                          "rest_on_ground": rest}}


def _sphere(subdivisions: int = 4) -> dict:
    return {"kind": "primitive", "primitive": "icosphere", "params": {"subdivisions": subdivisions}, "deform": None}


def _box(extents=(1.0, 1.0, 1.0)) -> dict:
    return {"kind": "primitive", "primitive": "box", "params": {"extents": list(extents)}, "deform": None}


def _rect_light(center, target, size, radiance, up=None) -> dict:
    c, t = np.asarray(center, float), np.asarray(target, float)
    n = (t - c) / np.linalg.norm(t - c)
    return {"type": "rectangle", "small": False, "center": list(map(float, center)), "normal": [round(float(x), 6) for x in n],
            "up": up or lt.perp_up(n), "size": list(size), "irradiance": None, "radiance": list(radiance)}


def _base(name: str, seed: int, frames: int) -> dict:
    return {"seed": int(seed), "index": None, "preset": name, "frames": int(frames), "objects": [], "ground": None,
            "walls": [], "lights": [], "environment": None}


def _cluster(desc: dict, center, radius) -> None:
    desc["cluster"] = {"center": [round(float(x), 4) for x in center], "radius": round(float(radius), 4)}


def stress_description(name: str, seed: int, frames: int) -> dict:
    if name not in STRESS_PRESETS:
        raise ValueError(f"unknown stress preset {name!r} (valid: {', '.join(STRESS_PRESETS)})")
    rng = np.random.default_rng([int(seed), zlib.crc32(name.encode())])
    d = _base(name, seed, frames)
    cfg = SceneConfig()

    if name == "tiny_bright_light":
        # A 1 cm sphere light delivering ordinary irradiance: radiance ~1e5, the fireflies case.
        d["objects"], center, radius = place_objects(rng, cfg, 4)
        c = np.asarray(center)
        d["camera"] = cam.random_camera(rng, c, radius, cfg.fov, 0.15, frames)
        dist = 2.5 * radius
        pos = c + lt.direction(rng.uniform(0, 360), rng.uniform(35, 70)) * dist
        light = {"type": "sphere", "small": True, "center": [round(float(x), 4) for x in pos], "radius": 0.005,
                 "irradiance": 3.0, "radiance": [round(3.0 * dist**2 / (np.pi * 0.005**2), 2)] * 3}
        d["lights"] = [light]
        half = d["camera"]["max_distance"] * 1.2 + radius
        d["ground"] = ground(center, 2 * half, GREY)
        d["walls"] = room_walls(center, half, 4 * radius + light["center"][1], ["+x", "-z", "-x"], WHITE)
        _cluster(d, center, radius)

    elif name == "caustics":
        # Glass focusing a small bright light onto a white ground; a metal ring adds a cardioid.
        d["objects"] = [
            _obj("glass_sphere", _sphere(5), GLASS, [0.0, 0.0, 0.0], 1.0),
            _obj("glass_vase", {"kind": "primitive", "primitive": "vase",
                                "params": {"radii": [0.4, 0.5, 0.3, 0.35], "height": 1.0, "sections": 64}, "deform": None},
                 {"family": "roughdielectric", "int_ior": 1.5, "ext_ior": 1.000277, "alpha": 0.05, "distribution": "ggx"},
                 [1.3, 0.0, -0.6], 0.8),
            _obj("metal_ring", {"kind": "primitive", "primitive": "torus",
                                "params": {"major_radius": 0.5, "minor_radius": 0.04, "major_sections": 96,
                                           "minor_sections": 16}, "deform": None},
                 {"family": "conductor", "material": "Au"}, [-1.3, 0.0, 0.4], 1.0),
        ]
        center, radius = [0.0, 0.4, 0.0], 2.0
        az = rng.uniform(0, 360)
        pos = np.asarray(center) + lt.direction(az, rng.uniform(45, 70)) * 3.5
        d["lights"] = [{"type": "sphere", "small": True, "center": [round(float(x), 4) for x in pos], "radius": 0.04,
                        "irradiance": 4.0, "radiance": [round(4.0 * 3.5**2 / (np.pi * 0.04**2), 2)] * 3}]
        d["environment"] = {"type": "constant", "irradiance": 0.05, "radiance": [0.016, 0.016, 0.02]}
        d["ground"] = ground(center, 40.0, WHITE)
        d["camera"] = cam.random_camera(rng, np.asarray(center), radius, [35.0, 50.0], 0.15, frames)
        _cluster(d, center, radius)

    elif name == "dark_room_gap":
        # A closed room; the only way in for light is a 6 cm slit in the ceiling under a bright panel.
        half, height, gap = 2.5, 2.6, 0.06
        d["objects"], center, radius = place_objects(rng, cfg, 3)
        c = [0.0, 0.0, 0.0]
        d["objects"] = [{**o, "transform": {**o["transform"], "position": [o["transform"]["position"][0] - center[0],
                                                                           o["transform"]["position"][1],
                                                                           o["transform"]["position"][2] - center[2]]}}
                        for o in d["objects"]]
        d["ground"] = ground(c, 2 * half, WHITE)
        d["walls"] = room_walls(c, half, height, ["+x", "-x", "+z", "-z"], WHITE)
        w = (half - gap / 2)  # two ceiling halves leave the slit along z at x = 0
        for sgn in (-1, 1):
            d["walls"].append(rect([sgn * (gap / 2 + w / 2), height, 0.0], [0, -1, 0], [0, 0, 1], [w, 2 * half], WHITE))
        d["lights"] = [_rect_light([0.0, height + 0.5, 0.0], [0.0, 0.0, 0.0], [1.0, 2 * half], [40.0, 38.0, 34.0])]
        d["environment"] = {"type": "constant", "irradiance": 3.0, "radiance": [0.95, 0.95, 1.0]}
        origin = [half * 0.8, 1.2, half * 0.8]
        d["camera"] = cam.static_camera(origin, [0.0, 0.4, 0.0], 60.0, frames, drift=[-0.2, 0.0, 0.1])
        _cluster(d, [0.0, 0.4, 0.0], 1.5)

    elif name == "mirrors":
        # Two parallel perfect mirrors: near-infinite chains of reflections, plus a mirror ball.
        d["objects"] = [
            _obj("mirror_ball", _sphere(5), MIRROR, [0.0, 0.0, 0.0], 0.8),
            _obj("box", _box([1.0, 1.0, 1.0]), {"family": "diffuse", "reflectance": [0.7, 0.2, 0.15]}, [0.3, 0.0, 1.0], 0.6,
                 (0, 30, 0)),
            _obj("sphere", _sphere(4), {"family": "roughplastic", "diffuse_reflectance": [0.1, 0.3, 0.7], "int_ior": 1.5,
                                        "alpha": 0.1, "distribution": "ggx", "nonlinear": False}, [-0.4, 0.0, -0.9], 0.6),
        ]
        mirror_mat = {"family": "conductor", "material": "Al"}
        d["walls"] = [rect([2.0, 1.5, 0.0], [-1, 0, 0], [0, 1, 0], [12.0, 3.0], mirror_mat),
                      rect([-2.0, 1.5, 0.0], [1, 0, 0], [0, 1, 0], [12.0, 3.0], mirror_mat)]
        d["ground"] = ground([0, 0, 0], 12.0, {"family": "diffuse",
                                               "reflectance": {"texture": {"kind": "checker", "seed": 0, "size": 256,
                                                                           "colors": [[0.05, 0.05, 0.05], [0.6, 0.6, 0.6]],
                                                                           "frequency": 8, "angle_deg": 0, "uv_scale": 3.0}}})
        d["lights"] = [_rect_light([0.0, 3.0, 0.5], [0.0, 0.0, 0.0], [1.0, 1.0], [15.0, 15.0, 15.0])]
        d["environment"] = {"type": "constant", "irradiance": 0.3, "radiance": [0.1, 0.1, 0.1]}
        origin = [1.2 + rng.uniform(-0.2, 0.2), 1.3, 3.0]  # between the mirrors, looking at one obliquely
        d["camera"] = cam.static_camera(origin, [-2.0, 0.6, -0.5], 55.0, frames, drift=[-0.3, 0.0, 0.0])
        _cluster(d, [0, 0.4, 0], 1.5)

    elif name == "emitter_fills_view":
        # The camera looks straight at a huge emitting panel: every pixel sees the light directly.
        radiance = (np.asarray(lt.light_color(rng)) * rng.uniform(0.5, 3.0)).round(4).tolist()
        d["lights"] = [_rect_light([0.0, 1.0, -2.0], [0.0, 1.0, 0.0], [60.0, 60.0], radiance, up=[0, 1, 0])]
        d["ground"] = ground([0, 0, 0], 40.0, GREY)
        d["objects"] = [_obj("behind_camera", _sphere(3), WHITE, [0.0, 0.0, 3.0], 1.0)]  # lit, but out of view
        # 1 unit from the panel: the steepest ray (22.5 deg) would meet the ground only 2.4 units away.
        d["camera"] = cam.static_camera([0.0, 1.0, -1.0], [0.0, 1.0, -2.0], 45.0, frames, drift=[0.2, 0.05, 0.0])
        _cluster(d, [0.0, 1.0, -2.0], 1.0)

    elif name == "empty_environment":
        # Nothing but the sky: no geometry at all.
        for _ in range(100):  # a sky (sometimes with a sun), not a constant
            env = lt.random_environment(rng, 3.0)
            if env["type"] == "sky":
                break
        d["environment"] = env
        d["camera"] = cam.static_camera([0.0, 1.0, 0.0], [0.0, 1.3, -1.0], 60.0, frames, drift=[0.0, 0.0, -0.1])
        d["camera"]["frames"] = [{**p, "target": [float(np.sin(0.3 * i)), 1.3, -float(np.cos(0.3 * i))]}
                                 for i, p in enumerate(d["camera"]["frames"])]  # pan: the view actually changes
        _cluster(d, [0.0, 1.0, 0.0], 1.0)

    else:  # degenerate_geometry
        raw_mat = {"family": "diffuse", "reflectance": [0.6, 0.55, 0.5]}
        zero_area = {"kind": "raw", "vertices": [[0, 0, 0], [1, 0, 0], [2, 0, 0],       # collinear
                                                  [0, 1, 0], [0, 1, 0], [0, 1, 0],       # coincident
                                                  [0, 0, 1], [1, 0, 1], [0, 1, 1]],      # one proper triangle
                     "faces": [[0, 1, 2], [3, 4, 5], [6, 7, 8], [6, 6, 7]]}
        duplicated = {"kind": "raw", "vertices": [[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 0], [0, 1, 0], [0, 0, 0]],
                      "faces": [[0, 1, 2], [3, 4, 5]]}  # a quad whose shared vertices are duplicated
        d["objects"] = [
            _obj("zero_area_triangles", zero_area, raw_mat, [-1.0, 0.3, 0.0], 1.0, two_sided=True, rest=False),
            _obj("duplicated_vertices", duplicated, raw_mat, [0.8, 0.2, -0.5], 1.0, (0, 20, 0), two_sided=True, rest=False),
            _obj("flat_box", _box([1.0, 1.0, 1.0]), {"family": "principled", "base_color": [0.2, 0.5, 0.8],
                                                      "roughness": 0.4, "metallic": 0.0, "specular": 0.5, "spec_trans": 0.0},
                 [0.0, 0.5, 0.8], [1.0, 0.0, 1.0]),
            _obj("tiny_sphere", _sphere(3), {"family": "diffuse", "reflectance": [0.9, 0.1, 0.1]}, [0.3, 0.2, 0.3], 1e-4),
            _obj("huge_box", _box(), {"family": "diffuse", "reflectance": [0.4, 0.4, 0.45]}, [0.0, 0.0, -3e4], 1e4),
            _obj("normal_sphere", _sphere(3), {"family": "roughconductor", "material": "Cu", "alpha": 0.2,
                                               "distribution": "ggx"}, [-0.3, 0.0, -0.6], 0.6),
        ]
        d["ground"] = ground([0, 0, 0], 40.0, GREY)
        d["lights"] = [_rect_light([1.0, 3.0, 2.0], [0.0, 0.0, 0.0], [1.0, 1.0], [8.0, 8.0, 8.0])]
        d["environment"] = {"type": "constant", "irradiance": 1.0, "radiance": [0.3, 0.3, 0.33]}
        center, radius = [0.0, 0.4, 0.0], 1.5
        d["camera"] = cam.random_camera(rng, np.asarray(center), radius, [45.0, 55.0], 0.1, frames)
        _cluster(d, center, radius)
    return d
