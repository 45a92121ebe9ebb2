"""Product shots (``scene.product_probability``): one to four glossy, metallic or glass products (bottles,
cans, phone-like slabs, watches, spheres, vases) on a seamless sweep (a floor curving up into a wall) or a
table, under studio lights (large softboxes, some dim, and strip lights: rectangular area lights aimed at
the products), seen close up through a tele-ish lens that moves a little over the frames.

The result is a scene description of render.scene (its ``kind`` is "product"), built and hashed as any.
"""
from __future__ import annotations

import numpy as np

from mcdenoise.render import camera as cam, furniture as fu, lights as lt
from mcdenoise.render.layout import rect
from mcdenoise.render.palette import glass, glazed, matte, metal, tone, wood
from mcdenoise.render.rounding import rnd, vec
from mcdenoise.render.textures import random_texture_params

PRODUCTS = ("bottle", "can", "phone", "watch", "sphere", "vase")


def product_scene(cfg, seed: int, index: int, frames: int) -> dict:
    """The description of product shot ``index`` of a dataset with master ``seed`` (its own stream)."""
    rng = np.random.default_rng([int(seed), int(index), 5])
    objects, ground = _set(rng)
    count = int(rng.integers(1, 5))
    xs = np.sort(rng.uniform(-0.12, 0.12, count)) * count
    for i, x in enumerate(xs):
        objects += _product(rng, PRODUCTS[int(rng.integers(len(PRODUCTS)))], i, [x, 0.0, rng.uniform(-0.12, 0.12)])
    tops = [max(p["position"][1] + p["size"][1] / 2 for p in o["shape"]["parts"]) for o in objects if o["name"].startswith("product")]
    center = np.array([float(np.mean(xs)), 0.5 * max(tops), 0.0])
    radius = float(max(np.ptp(xs) / 2 + 0.12, max(tops) * 0.7))
    camera = _camera(rng, center, radius, frames)
    lights, environment = _studio_lights(rng, center, radius, camera)
    return {"seed": int(seed), "index": int(index), "preset": None, "frames": int(frames),
            "kind": "product", "cluster": {"center": vec(center), "radius": rnd(radius)},
            "objects": objects, "ground": ground, "walls": [], "lights": lights, "environment": environment,
            "camera": camera}


def _still(name: str, parts: list, material: dict, two_sided: bool = False) -> dict:
    return {"name": name, "shape": {"kind": "assembly", "parts": parts}, "material": material, "two_sided": two_sided,
            "transform": {"scale": 1.0, "rotation_deg": [0.0, 0.0, 0.0], "position": [0.0, 0.0, 0.0]}}


def _set(rng) -> tuple[list, dict]:
    """A seamless paper sweep (60 %) or a table top with a plain wall far behind: (objects, ground)."""
    paper = matte(rng, sat=(0.0, 0.5), val=(0.05, 0.9)) if rng.uniform() < 0.7 else glazed(rng, (0.05, 0.3))
    if rng.uniform() < 0.6:
        w, h, d, r = 5.0, rng.uniform(2.0, 3.0), rng.uniform(2.5, 3.5), rng.uniform(0.5, 1.2)
        sweep = fu.part("sweep", [w, h, d], [0.0, h / 2, 1.5 - d / 2], width=w, height=h, depth=d, radius=r, sections=16)
        ground = rect([0.0, -0.01, 0.0], [0, 1, 0], [0, 0, 1], [40.0, 40.0], matte(rng, sat=(0, 0.1), val=(0.05, 0.3)))
        return [_still("sweep", [sweep], paper, two_sided=True)], ground
    top = wood(rng, 1.0, rnd(rng.uniform(0.05, 0.4))) if rng.uniform() < 0.6 else glazed(rng, (0.01, 0.2))
    table = [fu.part("box", [2.4, 0.05, 1.4], [0.0, -0.025, -0.2])]
    legs = [fu.part("box", [0.06, 0.7, 0.06], [sx * 1.1, -0.4, -0.2 + sz * 0.6]) for sx in (-1, 1) for sz in (-1, 1)]
    ground = rect([0.0, -0.75, 0.0], [0, 1, 0], [0, 0, 1], [40.0, 40.0], matte(rng, sat=(0, 0.2), val=(0.05, 0.4)))
    wall = _still("backdrop", [fu.part("box", [8.0, 5.0, 0.05], [0.0, 1.0, -rng.uniform(1.5, 3.0)])], paper)
    return [_still("table", table, top), _still("table_legs", legs, metal(rng)), wall], ground


def _product(rng, kind: str, i: int, at) -> list:
    """The objects of one product standing at ``at`` (its base on y = 0)."""
    x, _, z = at
    name = f"product_{i}.{kind}"
    if kind == "bottle":
        r, h = rng.uniform(0.03, 0.05), rng.uniform(0.18, 0.3)
        body = fu.vase_part([1, 1, 1, 0.95, 0.5, 0.32, 0.32], [2 * r, h, 2 * r], [x, h / 2, z])
        cap = fu.part("cylinder", [0.7 * r, 0.03, 0.7 * r], [x, h + 0.014, z])
        label = fu.part("cylinder", [2.02 * r, 0.35 * h, 2.02 * r], [x, 0.35 * h, z])
        return [_still(name, [body], glass(rng, 0.1)), _still(name + ".cap", [cap], metal(rng, (0.05, 0.3))),
                _still(name + ".label", [label], _label(rng))]
    if kind == "can":
        r, h = rng.uniform(0.03, 0.04), rng.uniform(0.1, 0.17)
        body = fu.part("cylinder", [2 * r, h, 2 * r], [x, h / 2, z], sections=48)
        rim = fu.part("torus", [2 * r, 0.006, 2 * r], [x, h, z], minor_radius=0.03)
        coat = {"family": "principled", "base_color": _label(rng)["base_color"], "metallic": rnd(rng.uniform(0.5, 1.0)),
                "roughness": rnd(rng.uniform(0.08, 0.35)), "specular": 0.5}
        return [_still(name, [body], coat), _still(name + ".rim", [rim], metal(rng, (0.03, 0.2)))]
    if kind == "phone":
        w, hh, t = rng.uniform(0.065, 0.08), rng.uniform(0.14, 0.17), rng.uniform(0.007, 0.01)
        lean, yaw = rng.uniform(-20, 0), rng.uniform(-30, 30)
        body = fu.part("box", [w, hh, t], [x, hh / 2 * np.cos(np.deg2rad(lean)), z], [lean, yaw, 0])
        screen = {"family": "principled", "base_color": [0.01, 0.01, 0.012], "roughness": 0.02, "metallic": 0.0,
                  "specular": 0.5, "clearcoat": 1.0, "clearcoat_gloss": 1.0}
        face = fu.part("box", [w * 0.94, hh * 0.96, 0.001], [x, hh / 2 * np.cos(np.deg2rad(lean)), z], [lean, yaw, 0])
        return [_still(name, [body], metal(rng, (0.02, 0.25))), _still(name + ".screen", [_offset(face, lean, yaw, t / 2)], screen)]
    if kind == "watch":
        r = rng.uniform(0.018, 0.025)
        case = fu.part("cylinder", [2 * r, 0.011, 2 * r], [x, 0.0055, z], sections=48)
        bezel = fu.part("torus", [2.1 * r, 0.004, 2.1 * r], [x, 0.011, z], minor_radius=0.06)
        crystal = fu.part("cylinder", [1.8 * r, 0.002, 1.8 * r], [x, 0.012, z], sections=48)
        straps = [fu.part("box", [1.1 * r, 0.004, 0.08], [x, 0.002, z + s * (r + 0.04)]) for s in (-1, 1)]
        leather = {"family": "principled", "base_color": tone(rng, (0.0, 0.12), (0.3, 0.8), (0.05, 0.4)),
                   "roughness": rnd(rng.uniform(0.3, 0.6)), "metallic": 0.0, "specular": 0.4}
        return [_still(name, [case, bezel], metal(rng, (0.01, 0.15))), _still(name + ".crystal", [crystal], glass(rng, 0.0)),
                _still(name + ".strap", straps, leather)]
    if kind == "sphere":
        r = rng.uniform(0.03, 0.08)
        mat = (metal(rng, (0.0, 0.1)), glass(rng, 0.2), glazed(rng, (0.005, 0.08)))[int(rng.integers(3))]
        return [_still(name, [fu.part("icosphere", [2 * r] * 3, [x, r, z], subdivisions=4)], mat)]
    r, h = rng.uniform(0.04, 0.09), rng.uniform(0.12, 0.32)
    body = fu.vase_part([rng.uniform(0.3, 1.0) for _ in range(5)], [2 * r, h, 2 * r], [x, h / 2, z])
    return [_still(name, [body], glazed(rng, (0.005, 0.1)) if rng.uniform() < 0.6 else glass(rng, 0.2))]


def _offset(p: dict, lean: float, yaw: float, by: float) -> dict:
    """``p`` moved ``by`` along the front normal of a slab leaning by ``lean`` and turned by ``yaw``."""
    a, b = np.deg2rad(lean), np.deg2rad(yaw)
    n = np.array([np.cos(a) * np.sin(b), -np.sin(a), np.cos(a) * np.cos(b)])
    return {**p, "position": vec(np.asarray(p["position"]) + n * (by + 0.0006))}


def _label(rng) -> dict:
    tex = random_texture_params(rng, size=128)
    tex["uv_scale"] = rnd(rng.uniform(3.0, 12.0))
    return {"family": "principled", "base_color": {"texture": tex}, "roughness": rnd(rng.uniform(0.2, 0.6)),
            "metallic": 0.0, "specular": 0.5}


def _camera(rng, center, radius: float, frames: int) -> dict:
    """Close, from the front (within 40 degrees of +z), a 15-35 degree lens, moving 3-8 % of its distance."""
    fov0 = rng.uniform(15.0, 35.0)
    az, el = np.deg2rad(90 + rng.uniform(-40, 40)), np.deg2rad(rng.uniform(4, 35))
    dist = cam.framing_distance(radius, fov0) * rng.uniform(0.85, 1.2)
    d = np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
    o0 = center + d * dist
    side = np.cross(d, cam.UP)
    side /= np.linalg.norm(side)
    step = side * rng.choice([-1, 1]) * dist * rng.uniform(0.03, 0.08)
    o2 = o0 + step + d * dist * rng.uniform(-0.03, 0.03)
    o1 = (o0 + o2) / 2 + np.array([0.0, dist * rng.uniform(-0.01, 0.01), 0.0])
    t0 = center + rng.normal(size=3) * radius * 0.05
    t2 = t0 + rng.normal(size=3) * radius * 0.03
    return cam.bezier_camera((o0, o1, o2), (t0, (t0 + t2) / 2, t2), (fov0, fov0 * rng.uniform(0.97, 1.03)), frames,
                             dist * 1.1)


def _studio_lights(rng, center, radius: float, camera: dict) -> tuple[list, dict | None]:
    """A key softbox, large dim fills and 0-2 strip lights, aimed at the products from outside the view."""
    avoid = [(np.asarray(p["origin"]) - center) / np.linalg.norm(np.asarray(p["origin"]) - center) for p in camera["frames"]]
    kinds = ["key"] + ["fill"] * int(rng.integers(0, 3)) + ["strip"] * int(rng.integers(0, 3))
    key = float(np.exp(rng.uniform(np.log(1.0), np.log(6.0))))      # irradiance at the products of the key light
    lights = []
    for kind in kinds:
        dist = rng.uniform(0.8, 2.0)
        d = _direction(rng, 5.0 if kind == "strip" else 15.0, avoid)
        if kind == "strip":
            w, h = rng.uniform(0.08, 0.2), rng.uniform(0.8, 1.6)
            e = key * rng.uniform(0.3, 2.0)
        else:
            w = rng.uniform(0.5, 1.5)
            h = w * rng.uniform(0.6, 1.0)
            e = key if kind == "key" else key * rng.uniform(0.05, 0.4)
        pos = center + d * dist
        n = -d
        up = [0.0, 1.0, 0.0] if kind == "strip" and abs(n[1]) < 0.9 else lt.perp_up(n)
        lights.append({"type": "rectangle", "role": kind, "small": False, "center": vec(pos), "normal": vec(n), "up": up,
                       "size": [rnd(w, 5), rnd(h, 5)], "irradiance": rnd(e),
                       "radiance": vec(np.asarray(lt.light_color(rng)) * e * dist**2 / (w * h))})
    env = None
    if rng.uniform() < 0.3:
        env = {"type": "constant", "irradiance": rnd(key * 0.05), "radiance": vec(np.asarray(lt.light_color(rng)) * key * 0.05 / np.pi)}
    return lights, env


def _direction(rng, min_elevation: float, avoid, min_angle_deg: float = 35.0) -> np.ndarray:
    """A direction from the products to a light, at least ``min_angle_deg`` from every camera direction (a
    softbox in view would fill the frame)."""
    for _ in range(64):
        d = lt.direction(rng.uniform(0, 360), rng.uniform(min_elevation, 75))
        if all(np.dot(d, a) < np.cos(np.deg2rad(min_angle_deg)) for a in avoid):
            break
    return d
