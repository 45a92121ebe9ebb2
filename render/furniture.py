"""Furniture and props of furnished rooms, assembled from primitives (``assembly`` shapes, render.geometry).

A builder returns an *item* in its own frame: the floor at y = 0, its footprint centred on the origin, its
front facing +z and its back at z = -depth/2 (against a wall). An item holds its parts grouped by the
material they take (``"parts": {role: [part, ...]}``; the room's palette gives each role a material), the
lights it carries (a lamp's bulb, in the same frame), its ``size`` [width, height, depth] and the
``surfaces`` props can stand on. ``place`` puts an item into the room as object and light descriptions.
"""
from __future__ import annotations

import numpy as np

from mcdenoise.render.rounding import rnd, vec

PART_DEFAULTS = {
    "box": {"extents": [1.0, 1.0, 1.0]},
    "cylinder": {"radius": 0.5, "height": 1.0, "sections": 24},
    "cone": {"radius": 0.5, "height": 1.0, "sections": 24},
    "icosphere": {"subdivisions": 2},
    "capsule": {"radius": 0.5, "height": 1.0, "count": [12, 12]},
    "torus": {"major_radius": 0.5, "minor_radius": 0.1, "major_sections": 32, "minor_sections": 12},
}


def part(primitive: str, size, position, rotation=None, **params) -> dict:
    """One primitive fitted to the box ``size`` (before it turns), turned by ``rotation`` (degrees, static x, y, z)
    and centred at ``position``."""
    p = {**PART_DEFAULTS.get(primitive, {}), **params}
    out = {"primitive": primitive, "params": p, "size": vec(size), "position": vec(position)}
    if rotation is not None:
        out["rotation_deg"] = vec(rotation)
    return out


def vase_part(radii, size, position) -> dict:
    """A closed body of revolution through ``radii`` (bottom to top), fitted to ``size``: bottles, glasses,
    bowls, pots."""
    return part("vase", size, position, radii=vec(radii), height=1.0, sections=24)


def item(size, parts: dict, surfaces=(), lights=(), name: str = "") -> dict:
    """An item; ``surfaces``: [x, y, z, width, depth, headroom] of each flat place props can stand on."""
    return {"name": name, "size": vec(size), "parts": parts, "surfaces": [list(s) for s in surfaces],
            "lights": list(lights)}


def u(rng, a: float, b: float) -> float:
    return rnd(rng.uniform(a, b))


# --------------------------------------------------------------------------------------------
# Furniture


def table(rng, w: float | None = None, d: float | None = None, h: float | None = None) -> dict:
    """A table: a top on four legs (square or round) or on a pedestal."""
    w, d, h = w or u(rng, 0.8, 1.8), d or u(rng, 0.6, 1.0), h or u(rng, 0.7, 0.78)
    t = u(rng, 0.025, 0.05)
    top = [part("box", [w, t, d], [0, h - t / 2, 0])]
    style = int(rng.integers(3))
    if style == 2:   # pedestal
        legs = [part("cylinder", [0.12, h - t, 0.12], [0, (h - t) / 2, 0]), part("cylinder", [0.5 * d, 0.03, 0.5 * d], [0, 0.015, 0])]
    else:
        leg = u(rng, 0.04, 0.07)
        prim = "box" if style == 0 else "cylinder"
        legs = [part(prim, [leg, h - t, leg], [sx * (w / 2 - leg), (h - t) / 2, sz * (d / 2 - leg)])
                for sx in (-1, 1) for sz in (-1, 1)]
    metal_legs = rng.uniform() < 0.3
    parts = {"wood": top} if metal_legs else {"wood": top + legs}
    if metal_legs:
        parts["metal"] = legs
    return item([w, h, d], parts, surfaces=[[0, h, 0, w - 0.1, d - 0.1, 0.8]], name="table")


def chair(rng) -> dict:
    w, d, seat = u(rng, 0.42, 0.5), u(rng, 0.42, 0.5), u(rng, 0.43, 0.48)
    back = u(rng, 0.35, 0.5)
    leg, t = 0.035, 0.04
    parts = [part("box", [w, t, d], [0, seat - t / 2, 0]),
             part("box", [w, back, 0.03], [0, seat + back / 2, -d / 2 + 0.015])]
    parts += [part("box", [leg, seat - t, leg], [sx * (w / 2 - leg), (seat - t) / 2, sz * (d / 2 - leg)])
              for sx in (-1, 1) for sz in (-1, 1)]
    return item([w, seat + back, d], {"wood": parts}, name="chair")


def shelf(rng) -> dict:
    """A bookcase: sides, a back, shelves with rows of books (three covers) and a few ornaments."""
    w, h, d = u(rng, 0.7, 1.6), u(rng, 1.0, 2.1), u(rng, 0.28, 0.4)
    t = 0.025
    n = max(2, int(h / u(rng, 0.3, 0.42)))
    ys = np.linspace(t / 2, h - t / 2, n + 1)
    wood = [part("box", [t, h, d], [sx * (w / 2 - t / 2), h / 2, 0]) for sx in (-1, 1)]
    wood += [part("box", [w, 0.01, d], [0, h / 2, -d / 2 + 0.005])]
    wood += [part("box", [w - 2 * t, t, d], [0, y, 0]) for y in ys]
    books: dict = {"book_a": [], "book_b": [], "book_c": []}
    surfaces = []
    for y0, y1 in zip(ys[:-1], ys[1:]):
        x, room = -w / 2 + t, y1 - y0 - t
        end = x + (w - 2 * t) * rng.uniform(0.3, 0.9)
        while x < end:
            bw, bh, bd = u(rng, 0.02, 0.06), room * rng.uniform(0.6, 0.92), d * rng.uniform(0.65, 0.9)
            if x + bw > w / 2 - t:
                break
            lean = 0.0 if rng.uniform() < 0.92 else u(rng, -12, 12)
            books[("book_a", "book_b", "book_c")[int(rng.integers(3))]].append(
                part("box", [bw, bh, bd], [x + bw / 2, y0 + t / 2 + bh / 2, -d / 2 + bd / 2 + 0.01], [0, 0, lean]))
            x += bw + (0.002 if rng.uniform() < 0.9 else 0.05)
        if w / 2 - t - x > 0.15:
            surfaces.append([(x + w / 2 - t) / 2, y0 + t / 2, 0, w / 2 - t - x - 0.04, d - 0.06, room])
    return item([w, h, d], {"wood": wood, **{k: v for k, v in books.items() if v}}, surfaces=surfaces, name="shelf")


def sofa(rng) -> dict:
    w, d = u(rng, 1.5, 2.4), u(rng, 0.8, 1.0)
    seat, back, arm = u(rng, 0.4, 0.46), u(rng, 0.75, 0.9), u(rng, 0.12, 0.22)
    n = int(rng.integers(2, 4))
    cw = (w - 2 * arm) / n
    fabric = [part("box", [w, seat - 0.15, d], [0, 0.08 + (seat - 0.15) / 2, 0]),
              part("box", [w, back - 0.08, 0.2], [0, 0.08 + (back - 0.08) / 2, -d / 2 + 0.1])]
    fabric += [part("box", [arm, u(rng, 0.55, 0.65) - 0.08, d], [sx * (w / 2 - arm / 2), 0.08 + 0.29, 0]) for sx in (-1, 1)]
    cushions = [part("box", [cw - 0.01, 0.15, d - 0.22], [-w / 2 + arm + cw * (i + 0.5), seat - 0.075, 0.1])
                for i in range(n)]
    cushions += [part("capsule", [0.4, 0.35, 0.14], [-w / 2 + arm + 0.3 + i * (w - 2 * arm - 0.6), seat + 0.17, -d / 2 + 0.28])
                 for i in range(2) if rng.uniform() < 0.7]
    legs = [part("cylinder", [0.04, 0.08, 0.04], [sx * (w / 2 - 0.06), 0.04, sz * (d / 2 - 0.06)])
            for sx in (-1, 1) for sz in (-1, 1)]
    return item([w, back, d], {"fabric": fabric, "cushion": cushions, "metal": legs}, name="sofa")


def bed(rng) -> dict:
    w, length = u(rng, 1.0, 1.8), u(rng, 2.0, 2.15)
    frame_h, mattress = u(rng, 0.25, 0.4), u(rng, 0.18, 0.25)
    head = u(rng, 0.9, 1.2)
    wood = [part("box", [w + 0.06, frame_h, length], [0, frame_h / 2, 0]),
            part("box", [w + 0.06, head, 0.06], [0, head / 2, -length / 2 + 0.03])]
    top = frame_h + mattress
    linen = [part("box", [w, mattress, length - 0.08], [0, frame_h + mattress / 2, 0.02])]
    # pillows: capsules squashed flat
    linen += [part("capsule", [0.6 if w > 1.2 else w - 0.2, 0.14, 0.38], [sx * (w / 4 if w > 1.2 else 0), top + 0.07, -length / 2 + 0.3])
              for sx in ((-1, 1) if w > 1.2 else (0,))]
    blanket = [part("box", [w + 0.08, 0.05, length * 0.62], [0, top + 0.01, length / 2 - length * 0.31 - 0.02])]
    return item([w + 0.08, head, length], {"wood": wood, "linen": linen, "fabric": blanket}, name="bed")


def cabinet(rng, tall: bool | None = None) -> dict:
    """A sideboard, a nightstand or (``tall``) a wardrobe: a body, door seams and handles; its top carries props."""
    tall = bool(rng.uniform() < 0.25) if tall is None else tall
    w = u(rng, 0.8, 1.6) if tall else u(rng, 0.4, 1.8)
    h = u(rng, 1.7, 2.2) if tall else u(rng, 0.45, 0.9)
    d = u(rng, 0.4, 0.6)
    doors = max(1, int(round(w / u(rng, 0.4, 0.6))))
    wood = [part("box", [w, h - 0.06, d], [0, 0.06 + (h - 0.06) / 2, 0])]
    seams = [part("box", [0.006, h - 0.12, 0.004], [-w / 2 + w * i / doors, 0.06 + (h - 0.06) / 2, d / 2 + 0.002])
             for i in range(1, doors)]
    handles = [part("cylinder", [0.015, 0.12, 0.015], [-w / 2 + w * (i + 0.5) / doors + (0.08 if i % 2 else -0.08) * (doors > 1),
                                                      0.06 + (h - 0.06) * (0.5 if tall else 0.75), d / 2 + 0.02]) for i in range(doors)]
    feet = [part("box", [0.05, 0.06, 0.05], [sx * (w / 2 - 0.05), 0.03, sz * (d / 2 - 0.05)]) for sx in (-1, 1) for sz in (-1, 1)]
    top = [0, h, 0, w - 0.08, d - 0.08, 0.3 if tall else 0.8]
    return item([w, h, d], {"wood": wood, "dark": seams, "metal": handles + feet}, surfaces=[top],
                name="wardrobe" if tall else "cabinet")


def picture(rng) -> dict:
    """A framed picture, hung on a wall (its back at the wall): a frame and a canvas (``art``)."""
    w, h = u(rng, 0.3, 1.1), u(rng, 0.3, 0.9)
    f, t = u(rng, 0.02, 0.06), 0.03
    # its bottom edge at y = 0, like the floor of a standing item: a pose's height is where it hangs
    frame = [part("box", [w, f, t], [0, h / 2 + sy * (h / 2 - f / 2), 0]) for sy in (-1, 1)]
    frame += [part("box", [f, h - 2 * f, t], [sx * (w / 2 - f / 2), h / 2, 0]) for sx in (-1, 1)]
    art = [part("box", [w - 2 * f, h - 2 * f, 0.01], [0, h / 2, -0.005])]
    return item([w, h, t], {"frame": frame, "art": art}, name="picture")


def rug(rng, w: float, d: float) -> dict:
    return item([w, 0.012, d], {"rug": [part("box", [w, 0.012, d], [0, 0.006, 0])]}, name="rug")


def plant(rng, scale: float = 1.0) -> dict:
    """A potted plant: a pot, soil and thin leaves fanning out upwards (two-sided, like real leaves)."""
    pot_r, pot_h = u(rng, 0.08, 0.2) * scale, u(rng, 0.12, 0.35) * scale
    pot = [vase_part([1.0, 0.9, 1.0, 1.1], [2 * pot_r, pot_h, 2 * pot_r], [0, pot_h / 2, 0])]
    soil = [part("cylinder", [1.8 * pot_r, 0.01, 1.8 * pot_r], [0, pot_h - 0.01, 0])]
    leaves = []
    n, reach = int(rng.integers(6, 16)), u(rng, 0.25, 0.8) * scale
    for _ in range(n):
        yaw, tilt = rng.uniform(0, 360), rng.uniform(10, 60)
        length = reach * rng.uniform(0.6, 1.0)
        a, t = np.deg2rad(yaw), np.deg2rad(tilt)
        # tilted about x, then turned about y (static xyz Euler angles): its long side points along ``tip``
        tip = np.array([np.sin(t) * np.sin(a), np.cos(t), np.sin(t) * np.cos(a)])
        leaves.append(part("box", [length * rng.uniform(0.12, 0.3), length, 0.002], tip * length / 2 + [0, pot_h, 0],
                           [tilt, yaw, 0]))
    top = pot_h + reach
    return item([max(2 * pot_r, reach), top, max(2 * pot_r, reach)], {"ceramic": pot, "dark": soil, "leaf": leaves},
                name="plant")


# --------------------------------------------------------------------------------------------
# Lamps: a bulb (a small, very bright sphere) inside a shade


def bulb(center, radius: float, power: float, color) -> dict:
    """A spherical bulb emitting ``power`` (flux = pi x radiance x area) in ``color`` (luminance ~1)."""
    radiance = np.asarray(color) * power / (4 * np.pi**2 * radius**2)
    return {"type": "sphere", "role": "bulb", "center": vec(center), "radius": rnd(radius, 6),
            "power": rnd(power), "radiance": vec(radiance)}


def _shade(rng, y0: float, scale: float, closed_top: bool) -> tuple[list, list, dict]:
    """A shade with its bottom at ``y0``: (shade parts, cap parts, its geometry for the bulb)."""
    bottom = u(rng, 0.14, 0.25) * scale
    top = bottom * rng.uniform(0.55, 1.0)
    h = u(rng, 0.16, 0.3) * scale
    shade = [part("frustum", [2 * bottom, h, 2 * bottom], [0, y0 + h / 2, 0], bottom=bottom, top=top, height=h, sections=32)]
    cap = [part("cylinder", [2 * top, 0.004, 2 * top], [0, y0 + h - 0.002, 0])] if closed_top else []
    return shade, cap, {"y0": y0, "height": h, "bottom": bottom, "top": top}


def _bulb_in(rng, g: dict, power: float, color) -> dict:
    """A bulb at the middle of a shade's height, well inside it."""
    r = u(rng, 0.015, 0.035)
    r = min(r, 0.3 * min(g["bottom"], g["top"]), 0.3 * g["height"])
    return bulb([0, g["y0"] + g["height"] * 0.5, 0], r, power, color)


def table_lamp(rng, power: float, color) -> dict:
    base_h = u(rng, 0.2, 0.45)
    base = [vase_part([u(rng, 0.4, 1.0) for _ in range(4)], [u(rng, 0.1, 0.2), base_h, u(rng, 0.1, 0.2)], [0, base_h / 2, 0])]
    stem = [part("cylinder", [0.015, 0.08, 0.015], [0, base_h + 0.04, 0])]
    shade, cap, g = _shade(rng, base_h + 0.02, 1.0, bool(rng.uniform() < 0.5))
    light = _bulb_in(rng, g, power, color)
    h = g["y0"] + g["height"]
    return item([2 * g["bottom"], h, 2 * g["bottom"]], {"ceramic": base, "metal": stem, "shade": shade + cap},
                lights=[{**light, "shade": g}], name="table_lamp")


def floor_lamp(rng, power: float, color) -> dict:
    pole_h = u(rng, 1.2, 1.6)
    metal = [part("cylinder", [0.3, 0.02, 0.3], [0, 0.01, 0]), part("cylinder", [0.025, pole_h, 0.025], [0, pole_h / 2, 0])]
    shade, cap, g = _shade(rng, pole_h - 0.05, 1.3, bool(rng.uniform() < 0.4))
    light = _bulb_in(rng, g, power, color)
    h = g["y0"] + g["height"]
    return item([max(0.3, 2 * g["bottom"]), h, max(0.3, 2 * g["bottom"])], {"metal": metal, "shade": shade + cap},
                lights=[{**light, "shade": g}], name="floor_lamp")


def pendant(rng, ceiling: float, power: float, color) -> dict:
    """A ceiling fixture on a cord: an open-bottomed shade whose bulb sits up inside it."""
    drop = u(rng, 0.4, min(1.0, ceiling - 1.9))
    shade, cap, g = _shade(rng, ceiling - drop - 0.25, 1.2, True)
    cord = [part("cylinder", [0.01, ceiling - g["y0"] - g["height"], 0.01],
                 [0, (ceiling + g["y0"] + g["height"]) / 2, 0])]
    light = _bulb_in(rng, g, power, color)
    return item([2 * g["bottom"], ceiling - g["y0"], 2 * g["bottom"]], {"metal": cord, "shade": shade + cap},
                lights=[{**light, "shade": g}], name="pendant")


# --------------------------------------------------------------------------------------------
# Props: small things on tables, shelves and cabinets


def prop(rng, room: float) -> dict:
    """A random small object at most ``room`` tall: a bottle, a glass, a bowl, a stack of books, a vase with
    twigs, a box or an ornament ball."""
    kind = ("bottle", "glass", "bowl", "books", "vase", "box", "ball")[int(rng.integers(7))]
    s = min(1.0, room / 0.35)
    if kind == "bottle":
        r, h = u(rng, 0.03, 0.05) * s, u(rng, 0.22, 0.33) * s
        body = vase_part([1, 1, 1, 0.9, 0.35, 0.3, 0.3], [2 * r, h, 2 * r], [0, h / 2, 0])
        return item([2 * r, h, 2 * r], {"glass": [body]}, name="bottle")
    if kind == "glass":
        r, h = u(rng, 0.03, 0.045) * s, u(rng, 0.08, 0.15) * s
        return item([2 * r, h, 2 * r], {"glass": [vase_part([0.8, 0.9, 1.0, 1.0], [2 * r, h, 2 * r], [0, h / 2, 0])]}, name="glass")
    if kind == "bowl":
        r, h = u(rng, 0.08, 0.15) * s, u(rng, 0.05, 0.1) * s
        return item([2 * r, h, 2 * r], {"ceramic": [vase_part([0.4, 0.8, 1.0], [2 * r, h, 2 * r], [0, h / 2, 0])]}, name="bowl")
    if kind == "books":
        parts, y = [], 0.0
        for _ in range(int(rng.integers(2, 5))):
            bh = u(rng, 0.02, 0.05) * s
            parts.append(part("box", [u(rng, 0.15, 0.25), bh, u(rng, 0.2, 0.28)], [0, y + bh / 2, 0], [0, u(rng, -10, 10), 0]))
            y += bh
        return item([0.3, y, 0.3], {"book_a": parts}, name="books")
    if kind == "vase":
        r, h = u(rng, 0.04, 0.08) * s, u(rng, 0.15, 0.3) * s
        body = [vase_part([u(rng, 0.4, 1.0) for _ in range(5)], [2 * r, h, 2 * r], [0, h / 2, 0])]
        twigs = [part("cylinder", [0.006, h, 0.006], [rng.uniform(-0.02, 0.02), h * 1.3, rng.uniform(-0.02, 0.02)],
                      [u(rng, -20, 20), 0, u(rng, -20, 20)]) for _ in range(int(rng.integers(0, 4)))]
        return item([2 * r, h * (1.8 if twigs else 1.0), 2 * r], {"ceramic": body, "dark": twigs}, name="vase")
    if kind == "box":
        w, h = u(rng, 0.08, 0.2) * s, u(rng, 0.04, 0.12) * s
        return item([w, h, w], {"accent": [part("box", [w, h, w * 0.8], [0, h / 2, 0])]}, name="box")
    r = u(rng, 0.03, 0.07) * s
    return item([2 * r, 2 * r, 2 * r], {"metal": [part("icosphere", [2 * r] * 3, [0, r, 0])]}, name="ball")


# --------------------------------------------------------------------------------------------
# Placing


def _turn(v, yaw_deg: float) -> np.ndarray:
    """``v`` (x, y, z) turned by ``yaw_deg`` about +y: +z goes to (sin, 0, cos), as geometry.transform_matrix does."""
    # The yaw case of render.camera.rotation, written out: Rodrigues' matrix product rounds differently in
    # the last bit, which moves some positions across the 4-decimal rounding of the descriptions, and the
    # generated scenes must stay as they were drawn (tests/test_interior.py pins the three against each other).
    a = np.deg2rad(yaw_deg)
    x, y, z = (float(c) for c in v)
    return np.array([x * np.cos(a) + z * np.sin(a), y, -x * np.sin(a) + z * np.cos(a)])


def to_world(point, pose) -> list:
    """A point of an item's frame in the room, for ``pose`` = (x, y, z, yaw_deg)."""
    return vec(_turn(point, pose[3]) + np.asarray(pose[:3], float))


def _light_to_world(light: dict, pose) -> dict:
    out = dict(light)
    for key in ("center", "position", "target"):
        if key in light:
            out[key] = to_world(light[key], pose)
    for key in ("normal", "up"):
        if key in light:
            out[key] = vec(_turn(light[key], pose[3]))
    if "shade" in light:   # the shade's axis in the room, for the checks that the bulb sits inside it
        out["shade"] = {**light["shade"], "axis": to_world([0, 0, 0], pose)}
    return out


def place(it: dict, name: str, pose, materials: dict, two_sided=("leaf", "shade", "art")) -> tuple[list, list]:
    """(object descriptions, light descriptions) of an item at ``pose``, one object per material role."""
    objects = []
    for role, parts in it["parts"].items():
        if not parts:
            continue
        objects.append({"name": f"{name}.{role}", "shape": {"kind": "assembly", "parts": parts},
                        "material": materials[role], "two_sided": role in two_sided,
                        "transform": {"scale": 1.0, "rotation_deg": [0.0, rnd(pose[3], 2), 0.0],
                                      "position": vec(pose[:3])}})
    return objects, [_light_to_world(light, pose) for light in it["lights"]]
