"""Stress presets: named, hand-built extreme scenes in the same description format as the random
ones (``render.scene``), rendered into the store's split ``stress`` (``dataset.stress``) to see where
a denoiser breaks.

Each preset is deterministic in (name, seed); the seed only varies the free details (object
shapes, colours, the camera path), never what makes the case extreme.
"""
from __future__ import annotations

import zlib

import numpy as np

from mcdenoise.pipeline.config import SceneConfig
from mcdenoise.render import camera as cam, lights as lt
from mcdenoise.render.layout import ground, place_objects, rect, room_walls

GREY = {"family": "diffuse", "reflectance": [0.5, 0.5, 0.5]}
WHITE = {"family": "diffuse", "reflectance": [0.75, 0.75, 0.75]}
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
    desc["cluster"] = {"center": _round4(center), "radius": round(float(radius), 4)}


def _round4(v) -> list[float]:
    return [round(float(x), 4) for x in v]


def _diffuse(rgb) -> dict:
    return {"family": "diffuse", "reflectance": list(rgb)}


def _constant_env(irradiance: float, radiance) -> dict:
    return {"type": "constant", "irradiance": irradiance, "radiance": list(radiance)}


def _small_sphere_light(position, radius: float, irradiance: float, distance: float) -> dict:
    """A small sphere light whose radiance delivers ``irradiance`` at ``distance``."""
    return {"type": "sphere", "small": True, "center": _round4(position), "radius": radius,
            "irradiance": irradiance, "radiance": [round(irradiance * distance**2 / (np.pi * radius**2), 2)] * 3}


def _recentred(objects: list[dict], center) -> list[dict]:
    """``objects`` moved so that ``center`` (their cluster's) stands over the origin; heights are kept."""
    return [{**o, "transform": {**o["transform"], "position": [o["transform"]["position"][0] - center[0],
                                                               o["transform"]["position"][1],
                                                               o["transform"]["position"][2] - center[2]]}}
            for o in objects]


# Each builder fills the description ``d`` of its preset, drawing only from ``rng``, and returns the
# (center, radius) of the cluster the camera frames.

def _tiny_bright_light(d: dict, rng, frames: int):
    """A 1 cm sphere light delivering ordinary irradiance: radiance ~1e5, the fireflies case."""
    cfg = SceneConfig()
    d["objects"], center, radius = place_objects(rng, cfg, 4)
    c = np.asarray(center)
    d["camera"] = cam.random_camera(rng, c, radius, cfg.fov, 0.15, frames)
    dist = 2.5 * radius
    pos = c + lt.direction(rng.uniform(0, 360), rng.uniform(35, 70)) * dist
    light = _small_sphere_light(pos, 0.005, 3.0, dist)
    d["lights"] = [light]
    half = d["camera"]["max_distance"] * 1.2 + radius
    d["ground"] = ground(center, 2 * half, GREY)
    d["walls"] = room_walls(center, half, 4 * radius + light["center"][1], ["+x", "-z", "-x"], WHITE)
    return center, radius


def _caustics(d: dict, rng, frames: int):
    """Glass focusing a small bright light onto a white ground; a metal ring adds a cardioid."""
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
    d["lights"] = [_small_sphere_light(pos, 0.04, 4.0, 3.5)]
    d["environment"] = _constant_env(0.05, [0.016, 0.016, 0.02])
    d["ground"] = ground(center, 40.0, WHITE)
    d["camera"] = cam.random_camera(rng, np.asarray(center), radius, [35.0, 50.0], 0.15, frames)
    return center, radius


def _dark_room_gap(d: dict, rng, frames: int):
    """A closed room; the only way in for light is a 6 cm slit in the ceiling under a bright panel."""
    half, height, gap = 2.5, 2.6, 0.06
    objects, center, _ = place_objects(rng, SceneConfig(), 3)
    d["objects"] = _recentred(objects, center)
    c = [0.0, 0.0, 0.0]
    d["ground"] = ground(c, 2 * half, WHITE)
    d["walls"] = room_walls(c, half, height, ["+x", "-x", "+z", "-z"], WHITE)
    w = (half - gap / 2)  # two ceiling halves leave the slit along z at x = 0
    for sgn in (-1, 1):
        d["walls"].append(rect([sgn * (gap / 2 + w / 2), height, 0.0], [0, -1, 0], [0, 0, 1], [w, 2 * half], WHITE))
    d["lights"] = [_rect_light([0.0, height + 0.5, 0.0], [0.0, 0.0, 0.0], [1.0, 2 * half], [40.0, 38.0, 34.0])]
    d["environment"] = _constant_env(3.0, [0.95, 0.95, 1.0])
    origin = [half * 0.8, 1.2, half * 0.8]
    d["camera"] = cam.static_camera(origin, [0.0, 0.4, 0.0], 60.0, frames, drift=[-0.2, 0.0, 0.1])
    return [0.0, 0.4, 0.0], 1.5


def _mirrors(d: dict, rng, frames: int):
    """Two parallel perfect mirrors: near-infinite chains of reflections, plus a mirror ball."""
    d["objects"] = [
        _obj("mirror_ball", _sphere(5), MIRROR, [0.0, 0.0, 0.0], 0.8),
        _obj("box", _box([1.0, 1.0, 1.0]), _diffuse([0.7, 0.2, 0.15]), [0.3, 0.0, 1.0], 0.6, (0, 30, 0)),
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
    d["environment"] = _constant_env(0.3, [0.1, 0.1, 0.1])
    origin = [1.2 + rng.uniform(-0.2, 0.2), 1.3, 3.0]  # between the mirrors, looking at one obliquely
    d["camera"] = cam.static_camera(origin, [-2.0, 0.6, -0.5], 55.0, frames, drift=[-0.3, 0.0, 0.0])
    return [0, 0.4, 0], 1.5


def _emitter_fills_view(d: dict, rng, frames: int):
    """The camera looks straight at a huge emitting panel: every pixel sees the light directly."""
    radiance = (np.asarray(lt.light_color(rng)) * rng.uniform(0.5, 3.0)).round(4).tolist()
    d["lights"] = [_rect_light([0.0, 1.0, -2.0], [0.0, 1.0, 0.0], [60.0, 60.0], radiance, up=[0, 1, 0])]
    d["ground"] = ground([0, 0, 0], 40.0, GREY)
    d["objects"] = [_obj("behind_camera", _sphere(3), WHITE, [0.0, 0.0, 3.0], 1.0)]  # lit, but out of view
    # 1 unit from the panel: the steepest ray (22.5 deg) would meet the ground only 2.4 units away.
    d["camera"] = cam.static_camera([0.0, 1.0, -1.0], [0.0, 1.0, -2.0], 45.0, frames, drift=[0.2, 0.05, 0.0])
    return [0.0, 1.0, -2.0], 1.0


def _random_sky(rng) -> dict:
    """A random sky environment (sometimes with a sun), not a constant; the last draw after 100 tries."""
    for _ in range(100):
        env = lt.random_environment(rng, 3.0)
        if env["type"] == "sky":
            break
    return env


def _empty_environment(d: dict, rng, frames: int):
    """Nothing but the sky: no geometry at all."""
    d["environment"] = _random_sky(rng)
    d["camera"] = cam.static_camera([0.0, 1.0, 0.0], [0.0, 1.3, -1.0], 60.0, frames, drift=[0.0, 0.0, -0.1])
    d["camera"]["frames"] = [{**p, "target": [float(np.sin(0.3 * i)), 1.3, -float(np.cos(0.3 * i))]}
                             for i, p in enumerate(d["camera"]["frames"])]  # pan: the view actually changes
    return [0.0, 1.0, 0.0], 1.0


def _degenerate_geometry(d: dict, rng, frames: int):
    """Meshes a renderer must survive: zero-area and duplicated-vertex triangles, a flat box, tiny and huge objects."""
    raw_mat = _diffuse([0.6, 0.55, 0.5])
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
        _obj("tiny_sphere", _sphere(3), _diffuse([0.9, 0.1, 0.1]), [0.3, 0.2, 0.3], 1e-4),
        _obj("huge_box", _box(), _diffuse([0.4, 0.4, 0.45]), [0.0, 0.0, -3e4], 1e4),
        _obj("normal_sphere", _sphere(3), {"family": "roughconductor", "material": "Cu", "alpha": 0.2,
                                           "distribution": "ggx"}, [-0.3, 0.0, -0.6], 0.6),
    ]
    d["ground"] = ground([0, 0, 0], 40.0, GREY)
    d["lights"] = [_rect_light([1.0, 3.0, 2.0], [0.0, 0.0, 0.0], [1.0, 1.0], [8.0, 8.0, 8.0])]
    d["environment"] = _constant_env(1.0, [0.3, 0.3, 0.33])
    center, radius = [0.0, 0.4, 0.0], 1.5
    d["camera"] = cam.random_camera(rng, np.asarray(center), radius, [45.0, 55.0], 0.1, frames)
    return center, radius


_BUILDERS = {"tiny_bright_light": _tiny_bright_light, "caustics": _caustics, "dark_room_gap": _dark_room_gap,
             "mirrors": _mirrors, "emitter_fills_view": _emitter_fills_view, "empty_environment": _empty_environment,
             "degenerate_geometry": _degenerate_geometry}

STRESS_PRESETS: tuple[str, ...] = tuple(_BUILDERS)


def stress_description(name: str, seed: int, frames: int) -> dict:
    """The scene description of stress preset ``name``: deterministic in (name, seed); ValueError for unknown names."""
    if name not in STRESS_PRESETS:
        raise ValueError(f"unknown stress preset {name!r} (valid: {', '.join(STRESS_PRESETS)})")
    rng = np.random.default_rng([int(seed), zlib.crc32(name.encode())])
    d = _base(name, seed, frames)
    center, radius = _BUILDERS[name](d, rng, frames)
    _cluster(d, center, radius)
    return d
