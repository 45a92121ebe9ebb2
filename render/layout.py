"""Scene layout helpers shared by the random scenes and the stress presets: object placement on the
ground, the ground plane and the walls of a room (all as JSON description fragments)."""
from __future__ import annotations

import numpy as np

from mcdenoise.render.geometry import random_shape
from mcdenoise.render.materials import pick_family, random_color, random_material
from mcdenoise.render.rounding import rnd, vec
from mcdenoise.render.textures import random_texture_params


def random_object(rng: np.random.Generator, cfg, mesh_files: tuple, name: str, position, scale) -> dict:
    shape = random_shape(rng, cfg.group_probability, mesh_files, cfg.mesh_probability)
    family = pick_family(rng, cfg.materials)
    mat = random_material(rng, family, cfg.texture_probability)
    if rng.uniform() < 0.3:  # stretched objects
        scale = [rnd(scale * rng.uniform(0.7, 1.3)) for _ in range(3)]
    tilt = rng.uniform() < 0.25
    rot = [rnd(rng.uniform(0, 360), 2) if tilt else 0.0, rnd(rng.uniform(0, 360), 2), rnd(rng.uniform(0, 360), 2) if tilt else 0.0]
    return {"name": name, "shape": shape, "material": mat,
            # User meshes may be open or inconsistently wound: shade both sides.
            "two_sided": shape["kind"] == "file",
            "transform": {"scale": scale, "rotation_deg": rot, "position": vec(position),
                          "rest_on_ground": True}}


def place_objects(rng: np.random.Generator, cfg, count: int, mesh_files: tuple = ()) -> tuple[list, list, float]:
    """Objects on the ground (a few floating) without heavy overlap; returns (objects, center, radius).

    ``transform.position[1]`` is the height of an object's lowest point, so 0 means resting on the
    ground. The cluster sphere bounds every object (a unit-box object scaled by s fits in radius
    0.87 s around its centre), which the camera and the lights aim at.
    """
    if count <= 0:  # nothing to frame: a patch of ground around the origin
        return [], [0.0, 0.5, 0.0], 1.0
    spread = 0.45 * np.sqrt(max(count, 1))
    placed: list[tuple[np.ndarray, float]] = []
    objects = []
    for i in range(count):
        s = float(rng.uniform(0.4, 1.1))
        best, best_gap = None, -np.inf
        for _ in range(30):  # rejection sampling: keep the candidate with the largest clearance
            p = rng.uniform(-spread, spread, 2)
            gap = min((np.linalg.norm(p - q) - 0.45 * (s + t) for q, t in placed), default=np.inf)
            if gap > best_gap:
                best, best_gap = p, gap
            if gap > 0:
                break
        placed.append((best, s))
        height = float(rng.uniform(0.1, 0.8)) if rng.uniform() < 0.1 else 0.0
        objects.append(random_object(rng, cfg, mesh_files, f"object_{i}", [best[0], height, best[1]], rnd(s)))
    centers = np.array([[o["transform"]["position"][0], o["transform"]["position"][1] + _size(o) / 2,
                         o["transform"]["position"][2]] for o in objects])
    center = centers.mean(0)
    radius = max(float(np.linalg.norm(c - center)) + 0.87 * _size(o) for c, o in zip(centers, objects))
    return objects, vec(center), rnd(radius)


def _size(obj: dict) -> float:
    return float(np.max(obj["transform"]["scale"]))


def surface_material(rng: np.random.Generator, texture_probability: float, size: float, tile: float,
                     polished_probability: float = 0.0) -> dict:
    """A matte-ish material for ground and walls; a texture repeats every ``tile`` units. With
    ``polished_probability`` it is polished instead (a smooth plastic or principled coat: sharp
    reflections of the lights and objects across a large plane, as floors and tiles of real interiors);
    at 0 no extra number is drawn, so scenes made before it existed are made the same."""
    polished = polished_probability > 0 and rng.uniform() < polished_probability
    family = ("diffuse", "roughplastic", "principled")[int(rng.choice(3, p=[0.5, 0.25, 0.25]))]
    if polished:
        family = "roughplastic" if family != "principled" else family
    mat = random_material(rng, family, 0.0)
    key = {"diffuse": "reflectance", "roughplastic": "diffuse_reflectance", "principled": "base_color"}[family]
    if family == "principled":
        rough = rng.uniform(0.02, 0.15) if polished else rng.uniform(0.3, 1.0)
        mat.update(metallic=0.0, spec_trans=0.0, roughness=rnd(rough))
        for k in ("clearcoat", "clearcoat_gloss", "sheen", "anisotropic"):
            mat.pop(k, None)
    elif polished:
        mat["alpha"] = rnd(rng.uniform(0.005, 0.06))
    if rng.uniform() < texture_probability:
        tex = random_texture_params(rng)
        tex["uv_scale"] = rnd(size / tile)
        mat[key] = {"texture": tex}
    else:
        mat[key] = random_color(rng, value=rng.uniform(0.3, 0.9))
    return mat


def rect(center, normal, up, size, material) -> dict:
    """A rectangle surface (Mitsuba ``rectangle``: [-1, 1]² scaled to ``size``, facing ``normal``)."""
    return {"center": vec(center), "normal": vec(normal), "up": vec(up), "size": [rnd(size[0]), rnd(size[1])],
            "material": material}


def ground(center, size: float, material: dict) -> dict:
    return rect([center[0], 0.0, center[2]], [0, 1, 0], [0, 0, 1], [size, size], material)


def room_walls(center, half: float, height: float, sides, material: dict, ceiling: bool = False,
               windows: dict | None = None) -> list:
    """Walls of a square room around ``center`` (sides among +x, -x, +z, -z), facing inwards; a side in
    ``windows`` has that opening (u0, u1, v0, v1) cut out of it (``wall_with_window``)."""
    cx, cz = center[0], center[2]
    walls = []
    for side in sides:
        axis, sign = ("x" if "x" in side else "z"), (1.0 if side.startswith("+") else -1.0)
        if axis == "x":
            c, n = [cx + sign * half, height / 2, cz], [-sign, 0, 0]
        else:
            c, n = [cx, height / 2, cz + sign * half], [0, 0, -sign]
        if windows and side in windows:
            walls += wall_with_window(c, n, 2 * half, height, windows[side], material)
        else:
            walls.append(rect(c, n, [0, 1, 0], [2 * half, height], material))
    if ceiling:
        walls.append(rect([cx, height, cz], [0, -1, 0], [0, 0, 1], [2 * half, 2 * half], material))
    return walls


def wall_with_window(center, normal, width: float, height: float, window, material: dict) -> list:
    """A wall of ``width`` × ``height`` standing on y = 0 (at ``center``'s x, z; facing ``normal``, horizontal)
    with a rectangular opening ``window`` = (u0, u1, v0, v1): u across the wall from its centre, v up from
    the floor. Four rectangles around the opening (the ones of zero size left out)."""
    n = np.asarray(normal, float)
    across = np.cross([0.0, 1.0, 0.0], n)
    u0, u1, v0, v1 = window
    pieces = [(-width / 2, u0, 0.0, height), (u1, width / 2, 0.0, height), (u0, u1, 0.0, v0), (u0, u1, v1, height)]
    out = []
    for a, b, lo, hi in pieces:
        if b - a > 1e-6 and hi - lo > 1e-6:
            c = np.array([center[0], 0.0, center[2]]) + across * (a + b) / 2 + np.array([0.0, (lo + hi) / 2, 0.0])
            out.append(rect(c, n, [0, 1, 0], [b - a, hi - lo], material))
    return out


def enclosed_room(rng: np.random.Generator, center, half: float, height: float, material: dict) -> list:
    """A closed room around ``center`` (four walls and a ceiling, facing inwards) whose only openings
    are one or two windows, each in its own wall: daylight from outside reaches the inside through
    them, mostly after bouncing off the walls and floor."""
    sides = ["+x", "-x", "+z", "-z"]
    windows = {}
    for k in sorted(rng.choice(4, size=int(rng.integers(1, 3)), replace=False).tolist()):
        w, h = 2 * half * rng.uniform(0.2, 0.6), height * rng.uniform(0.3, 0.6)
        u = rng.uniform(-half + w / 2, half - w / 2)
        sill = rng.uniform(0.05, 0.9) * (height - h)
        windows[sides[k]] = (u - w / 2, u + w / 2, sill, sill + h)
    return room_walls(center, half, height, sides, material, ceiling=True, windows=windows)
