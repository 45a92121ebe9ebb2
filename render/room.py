"""Floor plans of furnished rooms: a union of axis-aligned rectangles (the main room, an L-shaped wing, an
alcove, a neighbouring room through a door), the wall segments on its boundary, and the walls, floors and
ceilings they become (rectangles of render.layout, with windows and doors cut out).

A plan is ``{"height": h, "rects": [{"x": [x0, x1], "z": [z0, z1], "room": r}, ...]}``; room 0 is the one
the camera stands in, room 1 the neighbour. A segment lies on the line x = ``at`` (``line`` "x", spanning
z) or z = ``at`` (``line`` "z", spanning x), between ``rooms`` = (the label on its lower side, on its upper
side), -1 for outside.
"""
from __future__ import annotations

import numpy as np

from mcdenoise.render.layout import rect, wall_with_window
from mcdenoise.render.rounding import rnd


def random_plan(rng, neighbour: bool | None = None) -> dict:
    """A main room of 3.2-7 m by 3-6 m, 2.5-3.2 m high; an L wing (30 %), an alcove (30 %) and a neighbouring
    room behind a door (``neighbour``, else 50 %)."""
    w, d, h = rng.uniform(3.2, 7.0), rng.uniform(3.0, 6.0), rng.uniform(2.5, 3.2)
    rects = [{"x": [0.0, w], "z": [0.0, d], "room": 0}]
    if rng.uniform() < 0.3:   # an L: a wing along +x, shorter than the main room's depth
        rects.append({"x": [w, w + rng.uniform(1.5, 3.5)], "z": [0.0, d * rng.uniform(0.45, 0.7)], "room": 0})
    if rng.uniform() < 0.3:   # an alcove in the +z wall
        aw = rng.uniform(1.0, min(2.2, w - 0.6))
        a0 = rng.uniform(0.3, w - aw - 0.3)
        rects.append({"x": [a0, a0 + aw], "z": [d, d + rng.uniform(0.7, 1.5)], "room": 0})
    if neighbour if neighbour is not None else rng.uniform() < 0.5:   # next door, along -x
        # it shares at least 1.6 m of wall with the main room: room for a door
        z0 = rng.uniform(-1.0, d - 2.0)
        z1 = max(z0 + 2.5, 1.6, rng.uniform(z0 + 2.0, d + 1.5))
        rects.append({"x": [-rng.uniform(2.5, 4.5), 0.0], "z": [z0, z1], "room": 1})
    return {"height": rnd(h), "rects": [{**q, "x": [rnd(v) for v in q["x"]], "z": [rnd(v) for v in q["z"]]} for q in rects]}


def label_at(plan: dict, x: float, z: float) -> int:
    """The room at floor point (x, z), -1 outside."""
    for q in plan["rects"]:
        if q["x"][0] <= x <= q["x"][1] and q["z"][0] <= z <= q["z"][1]:
            return int(q["room"])
    return -1


def wall_segments(plan: dict) -> list:
    """The boundary of the plan's rooms as maximal straight segments, each between two different labels."""
    xs = sorted({v for q in plan["rects"] for v in q["x"]})
    zs = sorted({v for q in plan["rects"] for v in q["z"]})
    cx = [(a + b) / 2 for a, b in zip(xs[:-1], xs[1:])]
    cz = [(a + b) / 2 for a, b in zip(zs[:-1], zs[1:])]
    cells = np.array([[label_at(plan, x, z) for z in cz] for x in cx])     # [i along x, j along z]
    padded = np.pad(cells, 1, constant_values=-1)
    segments = []
    for line, lines, spans in (("x", xs, zs), ("z", zs, xs)):
        grid = padded if line == "x" else padded.T
        for i, at in enumerate(lines):
            lo, hi = grid[i, 1:-1], grid[i + 1, 1:-1]
            j = 0
            while j < len(spans) - 1:
                if lo[j] == hi[j]:
                    j += 1
                    continue
                k = j
                while k + 1 < len(spans) - 1 and (lo[k + 1], hi[k + 1]) == (lo[j], hi[j]):
                    k += 1
                segments.append({"line": line, "at": rnd(at), "span": [rnd(spans[j]), rnd(spans[k + 1])],
                                 "rooms": [int(lo[j]), int(hi[j])]})
                j = k + 1
    return segments


def inward(seg: dict, room: int) -> np.ndarray:
    """The unit normal of a segment pointing into ``room`` (one of its two sides), in x, y, z."""
    sign = 1.0 if seg["rooms"][1] == room else -1.0
    return np.array([sign, 0.0, 0.0]) if seg["line"] == "x" else np.array([0.0, 0.0, sign])


def point_on(seg: dict, s: float, y: float = 0.0) -> np.ndarray:
    """The point at line coordinate ``s`` along a segment, at height ``y``."""
    return np.array([seg["at"], y, s]) if seg["line"] == "x" else np.array([s, y, seg["at"]])


def segment_walls(seg: dict, height: float, material: dict, opening=None) -> list:
    """The rectangles of one wall segment, facing its room (both ways, two-sided, between two rooms), with
    ``opening`` = (s0, s1, v0, v1) cut out: line coordinates along it, heights up from the floor."""
    inner = -1 not in seg["rooms"]
    room = seg["rooms"][1] if inner or seg["rooms"][0] == -1 else seg["rooms"][0]
    n = inward(seg, room)
    mid = (seg["span"][0] + seg["span"][1]) / 2
    center = point_on(seg, mid)
    width = seg["span"][1] - seg["span"][0]
    if opening is None:
        walls = [rect(center + [0, height / 2, 0], n, [0, 1, 0], [width, height], material)]
    else:
        # wall_with_window measures u along cross(up, n); its component along the segment's line is k
        k = -n[0] if seg["line"] == "x" else n[2]
        s0, s1, v0, v1 = opening
        u0, u1 = sorted(((s0 - mid) * k, (s1 - mid) * k))
        walls = wall_with_window(center, n, width, height, (u0, u1, v0, v1), material)
    return [{**w, "two_sided": True} for w in walls] if inner else walls


def floors_and_ceilings(plan: dict, floor_mats: dict, ceiling: dict) -> list:
    """A floor (at y = 0, facing up) and a ceiling (facing down) over every rectangle of the plan."""
    out = []
    for q in plan["rects"]:
        c = [(q["x"][0] + q["x"][1]) / 2, 0.0, (q["z"][0] + q["z"][1]) / 2]
        size = [q["x"][1] - q["x"][0], q["z"][1] - q["z"][0]]
        out.append(rect(c, [0, 1, 0], [0, 0, 1], size, floor_mats[q["room"]]))
        out.append(rect([c[0], plan["height"], c[2]], [0, -1, 0], [0, 0, 1], size, ceiling))
    return out


def bounds(plan: dict) -> tuple:
    """(x0, x1, z0, z1) around the plan's rectangles."""
    qs = plan["rects"]
    return (min(q["x"][0] for q in qs), max(q["x"][1] for q in qs), min(q["z"][0] for q in qs), max(q["z"][1] for q in qs))
