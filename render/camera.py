"""Camera: look-at poses and a smooth random move over the frames of a scene.

The move is a quadratic Bezier through a start pose, a bent middle control point and an end pose
(origin, target and field of view are all interpolated), so consecutive frames differ by small,
smoothly varying steps like a hand-held or dolly shot. Every frame's pose is written out in the
description, so a reader never has to re-evaluate the curve.
"""
from __future__ import annotations

import numpy as np

UP = [0.0, 1.0, 0.0]


def _vec(v) -> list:
    return [round(float(x), 5) for x in v]


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
    ``targets``, its field of view going linearly from ``fovs[0]`` to ``fovs[1]``: every frame's pose."""
    (o0, o1, o2), (t0, t1, t2), (fov0, fov2) = origins, targets, fovs
    poses = []
    for i in range(frames):
        t = i / (frames - 1) if frames > 1 else 0.0
        poses.append({"origin": _vec(bezier(o0, o1, o2, t)), "target": _vec(bezier(t0, t1, t2, t)),
                      "up": list(UP), "fov": round(fov0 + (fov2 - fov0) * t, 4)})
    return {"path": "quadratic_bezier",
            "keyframes": {"origin": [_vec(o0), _vec(o1), _vec(o2)], "target": [_vec(t0), _vec(t1), _vec(t2)],
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
        poses.append({"origin": _vec(origin + drift * t), "target": _vec(target + drift * t * 0.5),
                      "up": [float(u) for u in up], "fov": round(float(fov), 4)})
    return {"path": "linear", "keyframes": {"origin": [_vec(origin), _vec(origin + drift)],
                                            "target": [_vec(target), _vec(target + drift * 0.5)], "fov": [fov, fov]},
            "max_distance": round(float(np.linalg.norm(origin - target) + np.linalg.norm(drift)), 5),
            "frames": poses}


def to_world(mi, pose: dict):
    return mi.ScalarTransform4f().look_at(origin=pose["origin"], target=pose["target"], up=pose["up"])
