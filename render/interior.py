"""Furnished interiors (``scene.interior_probability``): a room of varied plan (render.room) furnished from
render.furniture, lit the ways rooms are lit, seen by a camera standing inside it at eye height and
looking across it, moving a little over the frames.

Lighting, drawn per scene (``LIGHTINGS``): shaded lamps (a bulb inside a shade: table and floor lamps,
pendants over tables); daylight through windows (a sky, with a sun half of whose suns are delta lights);
both; a hidden cove light only (an emitter on a ledge below the ceiling, facing it, behind a fascia);
recessed downlights (spot lights just under the ceiling, never seen directly); light from the neighbouring
room only, through its door. Light powers within a scene differ by up to ~30x.

The result is a scene description of render.scene (its ``kind`` is "interior"), built and hashed as any.
"""
from __future__ import annotations

import numpy as np

from mcdenoise.render import camera as cam, furniture as fu, lights as lt
from mcdenoise.render.layout import rect
from mcdenoise.render.palette import art, floor, plaster, room_palette, tone
from mcdenoise.render.room import (
    bounds,
    floors_and_ceilings,
    inward,
    label_at,
    point_on,
    random_plan,
    segment_walls,
    wall_segments,
)
from mcdenoise.render.rounding import rnd, vec

LIGHTINGS = {"lamps": 0.22, "daylight": 0.2, "mixed": 0.16, "cove": 0.12, "neighbour": 0.14, "recessed": 0.16}
THEMES = ("living", "dining", "bedroom", "study")
CLEARANCE = 0.45   # free floor around the camera's path, in metres


class Layout:
    """Boxes (x0, x1, y0, y1, z0, z1) already taken in the room: furniture, the camera's path, the space in
    front of doors and windows."""

    def __init__(self):
        self.boxes: list = []

    def free(self, box, ignore=()) -> bool:
        return not any(i not in ignore and all(box[2 * k] < b[2 * k + 1] - 1e-3 and b[2 * k] < box[2 * k + 1] - 1e-3
                                               for k in range(3))
                       for i, b in enumerate(self.boxes))

    def take(self, box) -> int:
        self.boxes.append(tuple(float(v) for v in box))
        return len(self.boxes) - 1


def footprint(pose, size, y0: float = 0.0) -> tuple:
    """The box an item of ``size`` [w, h, d] takes at ``pose`` (x, y, z, yaw; yaw a multiple of 90 degrees)."""
    w, h, d = size
    if round(pose[3] / 90) % 2:
        w, d = d, w
    return (pose[0] - w / 2, pose[0] + w / 2, pose[1] + y0, pose[1] + y0 + h, pose[2] - d / 2, pose[2] + d / 2)


def _inside(plan, box, room: int) -> bool:
    x0, x1, _, _, z0, z1 = box
    return all(label_at(plan, x, z) == room for x in (x0 + 0.01, x1 - 0.01) for z in (z0 + 0.01, z1 - 0.01))


def interior_scene(cfg, seed: int, index: int, frames: int) -> dict:
    """The description of furnished interior ``index`` of a dataset with master ``seed`` (its own stream)."""
    rng = np.random.default_rng([int(seed), int(index), 4])
    names = list(LIGHTINGS)
    lighting = names[int(rng.choice(len(names), p=np.array([LIGHTINGS[n] for n in names]) / sum(LIGHTINGS.values())))]
    plan = random_plan(rng, neighbour=True if lighting == "neighbour" else None)
    # glossy floors sometimes, whatever the open scenes' polished_probability
    mats = room_palette(rng, max(float(cfg.polished_probability), 0.3))
    mats.update(neighbour_wall=plaster(rng), neighbour_floor=floor(rng, 0.3))
    layout = Layout()
    walls, openings = _walls(rng, plan, mats, lighting, layout)
    camera = _camera(rng, plan, frames, layout)
    room = _furnish(rng, plan, mats, layout)
    objects, surfaces = room.objects, room.surfaces
    more, lights, environment = _light(rng, lighting, plan, layout, room, openings)
    objects += more + _props(rng, surfaces, mats) + _pictures(rng, plan, mats, layout)
    x0, x1, z0, z1 = bounds(plan)
    c = [(x0 + x1) / 2, 0.0, (z0 + z1) / 2]
    outside = rect([c[0], -0.02, c[2]], [0, 1, 0], [0, 0, 1], [x1 - x0 + 60, z1 - z0 + 60], mats["outside"])
    main = plan["rects"][0]
    center = [(main["x"][0] + main["x"][1]) / 2, 1.0, (main["z"][0] + main["z"][1]) / 2]
    return {"seed": int(seed), "index": int(index), "preset": None, "frames": int(frames),
            "kind": "interior", "lighting": lighting, "plan": plan,
            "cluster": {"center": vec(center), "radius": rnd(np.hypot(x1 - x0, z1 - z0) / 2)},
            "objects": objects, "ground": outside, "walls": walls, "lights": lights, "environment": environment,
            "camera": camera}


# --------------------------------------------------------------------------------------------
# Walls, doors and windows


def _walls(rng, plan, mats, lighting: str, layout: Layout) -> tuple[list, list]:
    """Walls, floors and ceilings with doors between rooms and windows to outside: (rectangles, openings)."""
    h = plan["height"]
    daylight = lighting in ("daylight", "mixed")
    openings, walls = [], []
    segs = wall_segments(plan)
    outer = [i for i, s in enumerate(segs) if -1 in s["rooms"] and s["span"][1] - s["span"][0] >= 1.3]
    main_outer = [i for i in outer if 0 in segs[i]["rooms"]]
    window_at = {i for i in outer if rng.uniform() < (0.45 if daylight else 0.3)}
    if daylight and main_outer and not window_at & set(main_outer):
        window_at.add(main_outer[int(rng.integers(len(main_outer)))])
    if lighting == "neighbour":   # the main room has no windows: its light comes through the door
        window_at -= set(main_outer)
    for i, seg in enumerate(segs):
        length = seg["span"][1] - seg["span"][0]
        opening = None
        if -1 not in seg["rooms"] and length >= 1.1:
            w = rng.uniform(0.8, min(1.8, length - 0.3))
            s0 = rng.uniform(seg["span"][0] + 0.15, seg["span"][1] - 0.15 - w)
            opening = (s0, s0 + w, 0.0, rng.uniform(2.0, min(2.4, h - 0.1)))
            kind, depth = "door", 0.9
        elif i in window_at:
            w = rng.uniform(0.8, min(2.6, length - 0.4))
            s0 = rng.uniform(seg["span"][0] + 0.2, seg["span"][1] - 0.2 - w)
            sill = rng.uniform(0.3, 1.0)
            opening = (s0, s0 + w, sill, rng.uniform(min(sill + 1.0, h - 0.2), h - 0.15))
            kind, depth = "window", 0.35
        room = seg["rooms"][1] if seg["rooms"][0] == -1 else seg["rooms"][0]
        walls += segment_walls(seg, h, mats["wall"] if room == 0 else mats["neighbour_wall"], opening)
        if opening:
            openings.append({"kind": kind, "segment": seg, "span": vec(opening[:2]), "heights": vec(opening[2:])})
            a, b = point_on(seg, opening[0] - 0.1), point_on(seg, opening[1] + 0.1)
            n = inward(seg, room) * depth
            ends = np.array([a - n, b + n]) if kind == "door" else np.array([a, b + n])
            layout.take((ends[:, 0].min(), ends[:, 0].max(), opening[2], opening[3], ends[:, 2].min(), ends[:, 2].max()))
    floor_mats = {0: mats["floor"], 1: mats["neighbour_floor"]}
    return walls + floors_and_ceilings(plan, floor_mats, mats["ceiling"]), openings


# --------------------------------------------------------------------------------------------
# Camera


def _xz(axis: int, a: float, b: float, y: float) -> np.ndarray:
    """The point whose coordinate along ``axis`` (0: x, 1: z) is ``a`` and along the other ``b``, at height y."""
    return np.array([a, y, b]) if axis == 0 else np.array([b, y, a])


def _camera(rng, plan, frames: int, layout: Layout) -> dict:
    """A camera near one wall of the main room at eye height (standing, or seated a quarter of the time),
    looking across the room; it steps sideways 0.2-0.7 m over the frames. Its path is kept clear of furniture."""
    q = plan["rects"][0]
    lo, hi = np.array([q["x"][0], q["z"][0]]), np.array([q["x"][1], q["z"][1]])
    axis, sign = int(rng.integers(2)), (1.0 if rng.uniform() < 0.5 else -1.0)
    other = 1 - axis
    back = rng.uniform(0.4, 0.9)
    a0 = lo[axis] + back if sign > 0 else hi[axis] - back
    b0 = rng.uniform(lo[other] + 0.6, hi[other] - 0.6)
    eye = rng.uniform(1.45, 1.7) if rng.uniform() < 0.75 else rng.uniform(1.05, 1.25)
    b2 = float(np.clip(b0 + rng.choice([-1, 1]) * rng.uniform(0.2, 0.7), lo[other] + 0.5, hi[other] - 0.5))
    a2 = a0 + sign * rng.uniform(0.0, 0.35)
    a1, b1 = (a0 + a2) / 2 + sign * rng.uniform(-0.1, 0.15), (b0 + b2) / 2
    far = hi[axis] - 0.3 if sign > 0 else lo[axis] + 0.3
    tb0 = rng.uniform(lo[other] + 0.3, hi[other] - 0.3)
    tb2 = float(np.clip(tb0 + rng.uniform(-0.5, 0.5), lo[other], hi[other]))
    ty = rng.uniform(0.7, 1.3)
    origins = [_xz(axis, a0, b0, eye), _xz(axis, a1, b1, eye + rng.uniform(-0.03, 0.03)), _xz(axis, a2, b2, eye)]
    targets = [_xz(axis, far, tb0, ty), _xz(axis, far, (tb0 + tb2) / 2, ty), _xz(axis, far, tb2, ty + rng.uniform(-0.1, 0.1))]
    fov0 = rng.uniform(55.0, 80.0)
    camera = cam.bezier_camera(origins, targets, (fov0, fov0 * rng.uniform(0.95, 1.05)), frames,
                               float(np.linalg.norm(origins[0] - targets[0])))
    for t in np.linspace(0.0, 1.0, 9):
        p = cam.bezier(*origins, t)
        layout.take((p[0] - CLEARANCE, p[0] + CLEARANCE, 0.0, plan["height"], p[2] - CLEARANCE, p[2] + CLEARANCE))
    return camera


# --------------------------------------------------------------------------------------------
# Furniture


def on_wall(rng, it: dict, plan, layout: Layout, room: int, y: float = 0.0, tries: int = 24):
    """A pose with the item's back against a wall of ``room`` where it fits, taken in ``layout``; None if none."""
    segs = [s for s in wall_segments(plan) if room in s["rooms"]]
    w, _, d = it["size"]
    for _ in range(tries):
        seg = segs[int(rng.integers(len(segs)))]
        if seg["span"][1] - seg["span"][0] < w + 0.1:
            continue
        n = inward(seg, room)
        c = point_on(seg, rng.uniform(seg["span"][0] + w / 2 + 0.05, seg["span"][1] - w / 2 - 0.05)) + n * (d / 2 + 0.01)
        pose = (c[0], y, c[2], float(np.rad2deg(np.arctan2(n[0], n[2]))))
        box = footprint(pose, it["size"])
        if _inside(plan, box, room) and layout.free(box):
            layout.take(box)
            return pose
    return None


def _in_middle(rng, it: dict, plan, layout: Layout, tries: int = 24):
    """A pose for a free-standing item somewhere in the main room's floor; None if it does not fit."""
    x0, x1, z0, z1 = (*plan["rects"][0]["x"], *plan["rects"][0]["z"])
    for _ in range(tries):
        pose = (rng.uniform(x0 + 0.6, x1 - 0.6), 0.0, rng.uniform(z0 + 0.6, z1 - 0.6), 90.0 * int(rng.integers(4)))
        box = footprint(pose, it["size"])
        if _inside(plan, box, 0) and layout.free(box):
            layout.take(box)
            return pose
    return None


def _beside(it: dict, anchor, offset, turn: float, plan, layout: Layout, room: int, ignore=()):
    """The pose ``offset`` (in the anchor's frame) from ``anchor``, turned by ``turn``, if the item fits there."""
    pose = (*fu.to_world(offset, anchor), (anchor[3] + turn) % 360)
    box = footprint(pose, it["size"])
    if _inside(plan, box, room) and layout.free(box, ignore):
        return pose, layout.take(box)
    return None, None


class _Room:
    """Objects and prop surfaces gathered while furnishing."""

    def __init__(self, mats):
        self.mats, self.objects, self.surfaces, self.count = mats, [], [], 0
        self.over: list = []     # (x, z) of tables a pendant may hang over

    def name(self, it: dict, tag: str) -> str:
        """A name no other item of the scene has."""
        self.count += 1
        return f"{tag}_{self.count:03d}.{it['name']}"

    def add(self, it: dict, pose, tag: str):
        objects, _ = fu.place(it, self.name(it, tag), pose, self.mats)
        self.objects += objects
        for x, y, z, w, d, headroom in it["surfaces"]:
            self.surfaces.append({"pose": (*fu.to_world([x, y, z], pose), pose[3]), "size": [w, d], "headroom": headroom})


def _furnish(rng, plan, mats, layout: Layout) -> _Room:
    """Furniture of a theme (living room, dining room, bedroom, study) in the main room, a few pieces next
    door: its objects, the surfaces props and table lamps can stand on, the places pendants can hang."""
    room = _Room({**mats})
    theme = THEMES[int(rng.integers(len(THEMES)))]
    if theme == "living":
        _living(rng, plan, layout, room)
    elif theme == "dining":
        _dining(rng, plan, layout, room)
    elif theme == "bedroom":
        _bedroom(rng, plan, layout, room)
    else:
        desk = fu.table(rng, fu.u(rng, 1.0, 1.6), fu.u(rng, 0.6, 0.75), 0.74)
        pose = on_wall(rng, desk, plan, layout, 0)
        if pose:
            room.add(desk, pose, "desk")
            chair = fu.chair(rng)
            seat, _ = _beside(chair, pose, [0, 0, desk["size"][2] / 2 + 0.1], 180, plan, layout, 0, (len(layout.boxes) - 1,))
            if seat:
                room.add(chair, seat, "chair")
    extras = [fu.shelf, fu.cabinet, fu.plant, fu.shelf, fu.cabinet]
    for make in extras[: int(rng.integers(2, 6))]:
        _wall_piece(rng, make, plan, layout, room, 0, "wall")
    if any(q["room"] == 1 for q in plan["rects"]):
        for make in (fu.cabinet, fu.shelf, fu.plant)[: int(rng.integers(1, 4))]:
            _wall_piece(rng, make, plan, layout, room, 1, "next")
    return room


def _wall_piece(rng, make, plan, layout, room: _Room, where: int, tag: str) -> tuple:
    """(item, pose) of an item made by ``make`` and put against a wall of room ``where``; pose None if it fits nowhere."""
    it = make(rng)
    pose = on_wall(rng, it, plan, layout, where)
    if pose:
        room.add(it, pose, tag)
    return it, pose


def _living(rng, plan, layout, room: _Room) -> None:
    sofa, pose = _wall_piece(rng, fu.sofa, plan, layout, room, 0, "sofa")
    if pose is None:
        return
    coffee = fu.table(rng, fu.u(rng, 0.8, 1.2), fu.u(rng, 0.5, 0.7), fu.u(rng, 0.35, 0.45))
    offset = [0, 0, sofa["size"][2] / 2 + 0.4 + coffee["size"][2] / 2]
    at, _ = _beside(coffee, pose, offset, 0, plan, layout, 0)
    if at:
        room.add(coffee, at, "coffee")
        room.over.append((at[0], at[2]))
        rug = fu.rug(rng, coffee["size"][0] + fu.u(rng, 0.8, 1.6), coffee["size"][2] + fu.u(rng, 0.8, 1.4))
        if _inside(plan, footprint(at, rug["size"]), 0):
            room.add(rug, at, "rug")    # under the table: takes no floor of its own


def _dining(rng, plan, layout, room: _Room) -> None:
    table = fu.table(rng)
    pose = _in_middle(rng, table, plan, layout)
    if pose is None:
        return
    room.add(table, pose, "dining")
    taken = len(layout.boxes) - 1
    w, _, d = table["size"]
    for x in np.linspace(-w / 2, w / 2, max(1, int(w / 0.6)) + 2)[1:-1]:
        for side in (1, -1):
            chair = fu.chair(rng)
            at, _ = _beside(chair, pose, [x, 0, side * (d / 2 + 0.12)], 180 if side > 0 else 0, plan, layout, 0, (taken,))
            if at:
                room.add(chair, at, "chair")
    room.over.append((pose[0], pose[2]))


def _bedroom(rng, plan, layout, room: _Room) -> None:
    bed, pose = _wall_piece(rng, fu.bed, plan, layout, room, 0, "bed")
    if pose is None:
        return
    stand = fu.cabinet(rng, tall=False)
    stand["size"] = [min(stand["size"][0], 0.55), min(stand["size"][1], 0.6), min(stand["size"][2], 0.45)]
    stand = fu.item(stand["size"], {"wood": [fu.part("box", [stand["size"][0], stand["size"][1] - 0.06, stand["size"][2]],
                                                   [0, 0.06 + (stand["size"][1] - 0.06) / 2, 0])],
                                    "metal": [fu.part("box", [0.05, 0.06, 0.05], [0, 0.03, 0])]},
                    surfaces=[[0, stand["size"][1], 0, stand["size"][0] - 0.06, stand["size"][2] - 0.06, 0.8]], name="nightstand")
    for sx in (-1, 1):
        offset = [sx * (bed["size"][0] / 2 + stand["size"][0] / 2 + 0.04), 0, -bed["size"][2] / 2 + stand["size"][2] / 2]
        at, _ = _beside(stand, pose, offset, 0, plan, layout, 0)
        if at:
            room.add(stand, at, "stand")
    rug = fu.rug(rng, bed["size"][0] + 1.0, fu.u(rng, 1.0, 1.6))
    at = (*fu.to_world([0, 0, bed["size"][2] / 2], pose), pose[3])
    if rng.uniform() < 0.6 and _inside(plan, footprint(at, rug["size"]), 0):
        room.add(rug, at, "rug")


# --------------------------------------------------------------------------------------------
# Lights

POWER_PER_M2 = 8.0   # lamp flux per square metre of the main room: frame means ~0.02-0.5 (measured)


def _power(rng, base: float) -> float:
    """One source's flux: the scene's base times 0.06-2x, so the sources of a scene differ by up to ~30x."""
    return base * float(10 ** rng.uniform(-1.2, 0.3))


def _warm(rng) -> list:
    """A bulb's colour: warm white to neutral, luminance 1."""
    c = np.asarray(tone(rng, (0.05, 0.13), (0.0, 0.5), (1.0, 1.0)))
    return vec(c / max(0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2], 1e-6))


def _light(rng, lighting: str, plan, layout: Layout, room: _Room, openings) -> tuple[list, list, dict | None]:
    """The scene's light sources for its lighting: (their objects (shades, ledges, trims), lights, environment)."""
    q = plan["rects"][0]
    base = POWER_PER_M2 * (q["x"][1] - q["x"][0]) * (q["z"][1] - q["z"][0])
    objects, lights, env = [], [], None
    windows = [o for o in openings if o["kind"] == "window"]
    if lighting in ("lamps", "mixed") or (lighting == "recessed" and rng.uniform() < 0.5):
        for _ in range(int(rng.integers(1, 4 if lighting == "lamps" else 3))):
            o, li = _lamp(rng, plan, layout, room, _power(rng, base * (1.0 if lighting == "lamps" else 0.5)), 0)
            objects, lights = objects + o, lights + li
    if lighting in ("daylight", "mixed"):
        env = _sky(rng, rng.uniform(8.0, 50.0) * (0.5 if lighting == "mixed" else 1.0))
    elif lighting == "lamps" and windows and rng.uniform() < 0.4:
        env = _sky(rng, rng.uniform(0.5, 4.0))    # dusk outside
    if lighting == "cove" or (lighting in ("lamps", "mixed") and rng.uniform() < 0.2):
        segs = [s for s in wall_segments(plan) if 0 in s["rooms"] and s["span"][1] - s["span"][0] >= 1.5]
        for k in sorted(rng.choice(len(segs), size=min(len(segs), int(rng.integers(1, 3))), replace=False)):
            o, li = _cove(rng, segs[k], plan, layout, _power(rng, base * 2.0))
            objects, lights = objects + o, lights + [li]
    if lighting == "recessed":
        o, li = _recessed(rng, plan, base)
        objects, lights = objects + o, lights + li
    if lighting == "neighbour":
        o, li, env = _next_door(rng, plan, layout, room, base * 6.0, windows)
        objects, lights = objects + o, lights + li
    if not lights and env is None:   # never a black frame: a lamp after all
        o, li = _lamp(rng, plan, layout, room, _power(rng, base), 0)
        objects, lights = objects + o, lights + li
    return objects, lights, env


def _sky(rng, irradiance: float) -> dict:
    """A sky (a sun 70 % of the time, half of the suns delta lights) of ``irradiance`` outside."""
    sky = lt.random_environment(rng, irradiance)
    # random_environment gives a sky a sun 60 % of the time; redrawing 36 % of the sunless ones leaves
    # 0.6 / (0.6 + 0.4 * 0.64) = 70 % suns.
    while sky["type"] != "sky" or (sky["sun"] is None and rng.uniform() < 0.36):
        sky = lt.random_environment(rng, irradiance)
    if sky["sun"] and rng.uniform() < 0.5:
        sky = {**sky, "sun": {**sky["sun"], "delta": True}}
    return sky


def _lamp(rng, plan, layout: Layout, room: _Room, power: float, where: int) -> tuple[list, list]:
    """A shaded lamp in room ``where``: on a free table or cabinet top, standing by a wall, or hanging over a
    table (or anywhere from the ceiling); ([], []) where none fits."""
    kind = ("table", "floor", "pendant")[int(rng.integers(3))]
    color = _warm(rng)
    spots = [s for s in room.surfaces if s["headroom"] >= 0.6 and not s.get("used") and s["size"][0] >= 0.3]
    if kind == "table" and spots and where == 0:
        s = spots[int(rng.integers(len(spots)))]
        s["used"] = 0.45
        it = fu.table_lamp(rng, power, color)
        pose = (*fu.to_world([-s["size"][0] / 2 + 0.2, 0, 0], s["pose"]), s["pose"][3])
    elif kind == "pendant" and plan["height"] > 2.45:
        it = fu.pendant(rng, plan["height"], power, color)
        x, z = room.over.pop() if room.over and where == 0 else _free_spot(rng, plan, where)
        pose = (x, 0.0, z, 0.0)
        box = footprint(pose, it["size"], plan["height"] - it["size"][1])
        if not layout.free(box):
            return [], []
        layout.take(box)
    else:
        it = fu.floor_lamp(rng, power, color)
        pose = on_wall(rng, it, plan, layout, where)
        if pose is None:
            return [], []
    return fu.place(it, room.name(it, "lamp"), pose, room.mats)


def _free_spot(rng, plan, room: int) -> tuple:
    q = [r for r in plan["rects"] if r["room"] == room][0]
    return (rng.uniform(q["x"][0] + 0.5, q["x"][1] - 0.5), rng.uniform(q["z"][0] + 0.5, q["z"][1] - 0.5))


def _along(seg, along: float, across: float, height: float) -> list:
    """A box size for a piece running along a wall segment: ``along`` it, ``across`` out of the wall."""
    return [across, height, along] if seg["line"] == "x" else [along, height, across]


def _cove(rng, seg, plan, layout: Layout, power: float) -> tuple[list, dict]:
    """A cove light along a wall of the main room: an emitter on a ledge below the ceiling, facing the ceiling,
    behind a fascia and end caps. The camera stands below the ledge, so ledge and fascia hide the emitter."""
    h, n = plan["height"], inward(seg, 0)
    s0, s1 = seg["span"]
    length, mid = s1 - s0, (s0 + s1) / 2
    y, depth, t = h - rng.uniform(0.25, 0.4), rng.uniform(0.2, 0.3), 0.04
    at = lambda s, out, yy: point_on(seg, s, yy) + n * out  # noqa: E731
    parts = [fu.part("box", _along(seg, length, depth, t), at(mid, depth / 2, y - t / 2)),
             fu.part("box", _along(seg, length, 0.02, 0.16 + t), at(mid, depth - 0.01, y - t + (0.16 + t) / 2))]
    parts += [fu.part("box", _along(seg, 0.02, depth, 0.16 + t), at(s, depth / 2, y - t + (0.16 + t) / 2))
              for s in (s0 + 0.01, s1 - 0.01)]
    w_along, w_across = length - 0.12, depth - 0.08
    c = at(mid, 0.04 + w_across / 2, y + 0.005)
    size = [w_across, w_along] if seg["line"] == "x" else [w_along, w_across]
    light = {"type": "rectangle", "role": "cove", "hidden": True, "small": False, "center": vec(c),
             "normal": [0.0, 1.0, 0.0], "up": [0.0, 0.0, 1.0], "size": vec(size), "power": rnd(power),
             "radiance": vec(np.asarray(_warm(rng)) * power / (np.pi * w_along * w_across))}
    box = [at(s0, 0, y - t), at(s1, depth, y + 0.16)]
    layout.take((min(box[0][0], box[1][0]), max(box[0][0], box[1][0]), y - t, h,
                 min(box[0][2], box[1][2]), max(box[0][2], box[1][2])))
    obj = {"name": f"cove_{seg['line']}{seg['at']}", "shape": {"kind": "assembly", "parts": parts},
           "material": {"family": "diffuse", "reflectance": [0.75, 0.75, 0.75]}, "two_sided": False,
           "transform": {"scale": 1.0, "rotation_deg": [0.0, 0.0, 0.0], "position": [0.0, 0.0, 0.0]}}
    return [obj], light


def _recessed(rng, plan, base: float) -> tuple[list, list]:
    """Downlights in the main room's ceiling: spot lights just under it, each in a trim ring."""
    q, h = plan["rects"][0], plan["height"]
    nx, nz = int(rng.integers(1, 4)), int(rng.integers(1, 3))
    xs = np.linspace(*q["x"], nx + 2)[1:-1]
    zs = np.linspace(*q["z"], nz + 2)[1:-1]
    cutoff = rng.uniform(30.0, 55.0)
    each = base * rng.uniform(0.6, 1.5) / (nx * nz)
    lights, rings = [], []
    for x in xs:
        for z in zs:
            power = _power(rng, each * 2.0)
            intensity = np.asarray(_warm(rng)) * power / (2 * np.pi * (1 - np.cos(np.deg2rad(cutoff))))
            lights.append({"type": "spot", "role": "recessed", "hidden": True, "position": vec([x, h - 0.03, z]),
                           "target": vec([x, 0.0, z]), "cutoff_angle": rnd(cutoff, 2), "beam_width": rnd(cutoff * 0.7, 2),
                           "power": rnd(power), "intensity": vec(intensity)})
            rings.append(fu.part("torus", [0.16, 0.02, 0.16], [x, h - 0.01, z], minor_radius=0.12))
    obj = {"name": "downlight_trims", "shape": {"kind": "assembly", "parts": rings},
           "material": {"family": "roughconductor", "material": "Al", "alpha": 0.2, "distribution": "ggx"},
           "two_sided": False, "transform": {"scale": 1.0, "rotation_deg": [0.0, 0.0, 0.0], "position": [0.0, 0.0, 0.0]}}
    return [obj], lights


def _next_door(rng, plan, layout: Layout, room: _Room, power: float, windows) -> tuple[list, list, dict | None]:
    """Light in the neighbouring room only (the main room gets it through the door): a ceiling panel, a lamp or
    daylight through its window."""
    choice = rng.uniform()
    if choice < 0.25 and windows:
        return [], [], _sky(rng, rng.uniform(15.0, 80.0))
    if choice < 0.55:
        o, li = _lamp(rng, plan, layout, room, _power(rng, power), 1)
        if li:
            return o, li, None
    q = [r for r in plan["rects"] if r["room"] == 1][0]
    side = rng.uniform(0.4, 1.0)
    c = [(q["x"][0] + q["x"][1]) / 2, plan["height"] - 0.01, (q["z"][0] + q["z"][1]) / 2]
    p = _power(rng, power)
    return [], [{"type": "rectangle", "role": "panel", "small": False, "center": vec(c), "normal": [0.0, -1.0, 0.0],
                 "up": [0.0, 0.0, 1.0], "size": [rnd(side), rnd(side)], "power": rnd(p),
                 "radiance": vec(np.asarray(lt.light_color(rng)) * p / (np.pi * side * side))}], None


# --------------------------------------------------------------------------------------------
# Props and pictures


def _props(rng, surfaces: list, mats: dict) -> list:
    """Bottles, glasses, bowls, books, vases, boxes and balls on the free part of every surface."""
    objects = []
    for k, s in enumerate(surfaces):
        w, d = s["size"]
        lo = -w / 2 + s.get("used", 0.0) + 0.05
        count = int(rng.integers(0, max(1, int((w / 2 - lo) / 0.22)) + 1))
        for x in np.linspace(lo, w / 2 - 0.05, count + 2)[1:-1]:
            it = fu.prop(rng, s["headroom"])
            if max(it["size"][0], it["size"][2]) > min(d, 0.3) or it["size"][1] > s["headroom"]:
                continue
            z = rng.uniform(-(d - it["size"][2]) / 2, (d - it["size"][2]) / 2)
            pose = (*fu.to_world([x, 0, z], s["pose"]), float(rng.uniform(0, 360)))
            objects += fu.place(it, f"prop_{k:02d}_{len(objects):03d}.{it['name']}", pose, mats)[0]
    return objects


def _pictures(rng, plan, mats, layout: Layout) -> list:
    objects = []
    for i in range(int(rng.integers(0, 4))):
        it = fu.picture(rng)
        pose = on_wall(rng, it, plan, layout, 0, y=rng.uniform(1.1, 1.7), tries=8)
        if pose:
            objects += fu.place(it, f"picture_{i}", pose, {**mats, "art": art(rng)})[0]
    return objects
