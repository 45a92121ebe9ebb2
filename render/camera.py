"""Camera: look-at poses and a smooth random move over the frames of a scene.

The move is a quadratic Bezier through a start pose, a bent middle control point and an end pose
(origin, target and field of view are all interpolated), so consecutive frames differ by small,
smoothly varying steps like a hand-held or dolly shot. Every frame's pose is written out in the
description, so a reader never has to re-evaluate the curve.

A user's scene (``render-scene --frames N``) moves along a path from its own camera: an orbit about
the look-at target or a dolly towards it (``--move``, ``parse_move``, ``orbit_path``, ``dolly_path``),
or from its first camera to its second (``sensor_path``). These are pure functions of 4x4 matrices.
"""
from __future__ import annotations

import numpy as np

from mcdenoise.render.rounding import vec

UP = [0.0, 1.0, 0.0]


def bezier(p0, p1, p2, t: float) -> np.ndarray:
    p0, p1, p2 = (np.asarray(p, dtype=np.float64) for p in (p0, p1, p2))
    return (1 - t) ** 2 * p0 + 2 * t * (1 - t) * p1 + t * t * p2


def framing_distance(radius: float, fov_deg: float) -> float:
    """Distance at which a sphere of ``radius`` just fits a field of view of ``fov_deg``."""
    return radius / np.sin(np.deg2rad(fov_deg) / 2)


def random_camera(rng: np.random.Generator, center, radius: float, fov_range, move: float, frames: int,
                  min_height: float = 0.05) -> dict:
    """Camera keyframes looking at a cluster (center, radius), and the pose of every frame."""
    center = np.asarray(center, dtype=np.float64)
    fov0 = float(rng.uniform(*fov_range))
    az, el = rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(8, 40))
    # The cluster radius is a loose bound (every object counted as its bounding sphere), so "just
    # fits" at 0.8-1.05 x keeps the objects in view while filling the frame; the move is mostly sideways.
    dist = framing_distance(radius, fov0) * rng.uniform(0.8, 1.05) * (1 + 0.25 * move)
    dirv = np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
    o0 = center + dirv * dist
    step = rng.normal(size=3)
    step[1] *= 0.3  # mostly sideways/forward moves: strong vertical moves look unnatural
    step /= max(np.linalg.norm(step), 1e-9)
    length = move * dist
    o2 = o0 + step * length
    side = np.cross(step, UP)
    side = side / max(np.linalg.norm(side), 1e-9) if np.linalg.norm(side) > 1e-6 else np.array([1.0, 0, 0])
    o1 = (o0 + o2) / 2 + side * length * rng.uniform(-0.35, 0.35)  # bends the path
    for o in (o0, o1, o2):
        o[1] = max(o[1], min_height)  # never below the ground
    t0 = center + rng.normal(size=3) * radius * 0.1
    t2 = center + rng.normal(size=3) * radius * 0.1
    t1 = (t0 + t2) / 2
    fov2 = float(np.clip(fov0 * rng.uniform(0.92, 1.08), *fov_range))
    return bezier_camera((o0, o1, o2), (t0, t1, t2), (fov0, fov2), frames, dist + length)


def bezier_camera(origins, targets, fovs, frames: int, max_distance: float) -> dict:
    """The camera description of a move along quadratic Beziers through three ``origins`` and three
    ``targets``, its field of view going linearly from ``fovs[0]`` to ``fovs[1]``: every frame's pose.

    ``max_distance`` is stored as given (the description's ``max_distance``). Only the open sets and the
    stress presets read it, as how far the camera gets from the scene's centre, to size the room around
    the path (render.scene, render.stress): ``random_camera`` passes the start distance from the centre
    plus the move's length. Interiors pass the start origin's distance to its target and product shots 1.1
    times the start distance to the products; nothing is built from those."""
    (o0, o1, o2), (t0, t1, t2), (fov0, fov2) = origins, targets, fovs
    poses = []
    for i in range(frames):
        t = i / (frames - 1) if frames > 1 else 0.0
        poses.append({"origin": vec(bezier(o0, o1, o2, t), 5), "target": vec(bezier(t0, t1, t2, t), 5),
                      "up": list(UP), "fov": round(fov0 + (fov2 - fov0) * t, 4)})
    return {"path": "quadratic_bezier",
            "keyframes": {"origin": [vec(o0, 5), vec(o1, 5), vec(o2, 5)], "target": [vec(t0, 5), vec(t1, 5), vec(t2, 5)],
                          "fov": [round(fov0, 4), round(fov2, 4)]},
            "max_distance": round(float(max_distance), 5),
            "frames": poses}


def static_camera(origin, target, fov: float, frames: int, up=UP, drift=None) -> dict:
    """A fixed pose (optionally drifting linearly by ``drift``) for hand-made stress scenes."""
    origin, target = np.asarray(origin, float), np.asarray(target, float)
    drift = np.zeros(3) if drift is None else np.asarray(drift, float)
    poses = []
    for i in range(frames):
        t = i / (frames - 1) if frames > 1 else 0.0
        poses.append({"origin": vec(origin + drift * t, 5), "target": vec(target + drift * t * 0.5, 5),
                      "up": [float(u) for u in up], "fov": round(float(fov), 4)})
    return {"path": "linear", "keyframes": {"origin": [vec(origin, 5), vec(origin + drift, 5)],
                                            "target": [vec(target, 5), vec(target + drift * 0.5, 5)], "fov": [fov, fov]},
            "max_distance": round(float(np.linalg.norm(origin - target) + np.linalg.norm(drift)), 5),
            "frames": poses}


def to_world(mi, pose: dict):
    return mi.ScalarTransform4f().look_at(origin=pose["origin"], target=pose["target"], up=pose["up"])


# ---- camera paths of a user's scene (render-scene --frames N [--move ...]) ------------------------
# A path is N camera_to_world matrices (Mitsuba's to_world: columns left, up, forward, origin) from the
# scene's own camera: frame 0 is always that camera, so frame 0 of a sequence is the single-frame render.

MOVES = ("orbit", "dolly")


def parse_move(text: str) -> tuple[str, float]:
    """``orbit:DEGREES`` or ``dolly:FRACTION`` as (kind, amount); ValueError in one line otherwise."""
    import re
    m = re.fullmatch(r"(\w+):([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)", text.strip())
    if not m or m.group(1) not in MOVES:
        raise ValueError(f"--move {text!r}: expected orbit:DEGREES (around the look-at target) or dolly:FRACTION "
                         "(towards it, a fraction of the distance), e.g. orbit:10 or dolly:0.2")
    kind, amount = m.group(1), float(m.group(2))
    if kind == "orbit" and not abs(amount) <= 360:
        raise ValueError(f"--move {text!r}: an orbit of at most 360 degrees either way")
    if kind == "dolly" and not amount < 1:
        raise ValueError(f"--move {text!r}: a dolly moves by a fraction of the distance to the target below 1 "
                         "(1 would reach it; negative values move away)")
    return kind, amount


def _fractions(frames: int) -> np.ndarray:
    return np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)


def rotation(axis, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about ``axis`` (right-handed; Rodrigues' formula)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def orbit_path(camera_to_world, distance: float, degrees: float, frames: int) -> list[np.ndarray]:
    """The camera turned about the vertical axis through its look-at target (the point ``distance``
    ahead on its view axis; vertical: the camera's own up, so a tilted camera keeps its tilt and the
    target stays in the image centre) by ``degrees`` over the frames, evenly. Positive angles are
    counter-clockwise seen from above: the camera moves to its right."""
    m = np.asarray(camera_to_world, dtype=np.float64)
    target = m[:3, 3] + distance * m[:3, 2] / np.linalg.norm(m[:3, 2])
    out = []
    for s in _fractions(frames):
        r = rotation(m[:3, 1], np.radians(degrees) * s)
        pose = m.copy()
        pose[:3, :3] = r @ m[:3, :3]
        pose[:3, 3] = target + r @ (m[:3, 3] - target)
        out.append(pose)
    return out


def dolly_path(camera_to_world, distance: float, fraction: float, frames: int) -> list[np.ndarray]:
    """The camera moved along its view axis towards the target ``distance`` ahead by ``fraction`` of that
    distance over the frames, evenly (negative: away from it); the orientation stays."""
    m = np.asarray(camera_to_world, dtype=np.float64)
    forward = m[:3, 2] / np.linalg.norm(m[:3, 2])
    out = []
    for s in _fractions(frames):
        pose = m.copy()
        pose[:3, 3] = m[:3, 3] + forward * distance * fraction * s
        out.append(pose)
    return out


def _quaternion(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a 3x3 rotation (Shepperd's method: the largest pivot, stable)."""
    tr = np.trace(r)
    pivots = [tr, r[0, 0], r[1, 1], r[2, 2]]
    k = int(np.argmax(pivots))
    if k == 0:
        w = np.sqrt(1 + tr) / 2
        q = [w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)]
    else:
        i, j, n = k - 1, k % 3, (k + 1) % 3        # the largest diagonal entry and the next two, cyclic
        v = np.zeros(3)
        v[i] = np.sqrt(1 + r[i, i] - r[j, j] - r[n, n]) / 2
        v[j] = (r[j, i] + r[i, j]) / (4 * v[i])
        v[n] = (r[n, i] + r[i, n]) / (4 * v[i])
        q = [(r[n, j] - r[j, n]) / (4 * v[i]), *v]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions along the shorter arc."""
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:                          # nearly equal: the linear blend is the same to 1e-7
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    angle = np.arccos(dot)
    return (np.sin((1 - s) * angle) * q0 + np.sin(s * angle) * q1) / np.sin(angle)


def sensor_path(first, second, frames: int) -> list[np.ndarray]:
    """From the pose ``first`` to ``second`` (camera_to_world each) over the frames, evenly: the origin
    along the straight line, the orientation by spherical interpolation of the rotations (constant
    angular speed on the shorter arc, so the view turns smoothly and the up vector never flips). A
    mirrored camera (a negative determinant, as XML written by some exporters has) is interpolated as
    its mirror image; ValueError if only one of the two is mirrored."""
    a, b = (np.asarray(m, dtype=np.float64) for m in (first, second))
    mirror = np.diag([-1.0, 1.0, 1.0])
    signs = [np.linalg.det(m[:3, :3]) < 0 for m in (a, b)]
    if signs[0] != signs[1]:
        raise ValueError("the two cameras differ in handedness (one is mirrored): no rotation leads from one to the other")
    ra, rb = ((m[:3, :3] @ mirror if signs[0] else m[:3, :3]) for m in (a, b))
    qa, qb = _quaternion(ra), _quaternion(rb)
    out = []
    for s in _fractions(frames):
        pose = np.eye(4)
        r = _matrix(slerp(qa, qb, s))
        pose[:3, :3] = r @ mirror if signs[0] else r
        pose[:3, 3] = (1 - s) * a[:3, 3] + s * b[:3, 3]
        out.append(pose)
    return out
