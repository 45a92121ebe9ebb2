"""Lights: area emitters (rectangles, spheres), point and spot lights, and environments.

Light strengths are set from a target *irradiance* at the object cluster rather than drawn as raw
radiance: a small light then automatically gets a huge radiance (the stiff, noisy case the denoiser
must learn) while the image brightness stays in a sane range. The description keeps both the
target (``irradiance``) and the resulting plugin value (``radiance``/``intensity``/``scale``).
"""
from __future__ import annotations

import numpy as np

from mcdenoise.render.rounding import rnd, vec
from mcdenoise.render.textures import random_color

SKY_SIZE = (64, 128)  # latlong (rows, cols): small, since the sky is smooth apart from the sun


def light_color(rng: np.random.Generator) -> list:
    """A mildly tinted light colour with luminance ~1 (warm, cool or white)."""
    c = np.asarray(random_color(rng, saturation=rng.uniform(0.0, 0.35), value=1.0))
    lum = 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
    return vec(c / max(lum, 1e-6))


def direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector; y is up, azimuth measured in the xz plane from +x towards +z."""
    a, e = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    return np.array([np.cos(e) * np.cos(a), np.sin(e), np.cos(e) * np.sin(a)])


def perp_up(n: np.ndarray) -> list:
    """An 'up' vector not parallel to n (look_at needs one)."""
    n = np.asarray(n, dtype=np.float64) / max(float(np.linalg.norm(n)), 1e-12)
    return [0.0, 0.0, 1.0] if abs(n[1]) > 0.95 else [0.0, 1.0, 0.0]


def _light_direction(rng: np.random.Generator, min_elevation: float, avoid=(), min_angle_deg: float = 30.0):
    """A direction from the cluster to a light, not within min_angle_deg of any ``avoid`` direction
    (the camera's): a big light between camera and objects would fill the frame."""
    for _ in range(32):
        d = direction(rng.uniform(0, 360), rng.uniform(min_elevation, 80))
        if all(np.dot(d, a) < np.cos(np.deg2rad(min_angle_deg)) for a in avoid):
            break
    return d


def area_light(rng: np.random.Generator, center: np.ndarray, radius: float, max_dist: float,
               irradiance: float, small: bool, avoid=()) -> dict:
    """A rectangle or sphere emitter above the cluster, facing it."""
    dist = min(radius * rng.uniform(1.5, 4.0), max_dist)
    pos = center + _light_direction(rng, 25, avoid) * dist
    size = radius * (rng.uniform(0.01, 0.06) if small else rng.uniform(0.25, 1.0))
    color = np.asarray(light_color(rng))
    if rng.uniform() < 0.5:
        w, h = size, size * rng.uniform(0.3, 1.0)
        area = w * h
        n = (center - pos) / np.linalg.norm(center - pos)
        return {"type": "rectangle", "small": bool(small), "center": vec(pos), "normal": vec(n),
                "up": perp_up(n), "size": [rnd(w, 6), rnd(h, 6)], "irradiance": rnd(irradiance),
                "radiance": vec(color * irradiance * dist**2 / area)}
    r = size / 2
    return {"type": "sphere", "small": bool(small), "center": vec(pos), "radius": rnd(r, 6),
            "irradiance": rnd(irradiance), "radiance": vec(color * irradiance * dist**2 / (np.pi * r * r))}


def point_light(rng: np.random.Generator, center: np.ndarray, radius: float, max_dist: float,
                irradiance: float) -> dict:
    dist = min(radius * rng.uniform(1.2, 3.5), max_dist)
    pos = center + direction(rng.uniform(0, 360), rng.uniform(20, 85)) * dist
    return {"type": "point", "position": vec(pos), "irradiance": rnd(irradiance),
            "intensity": vec(np.asarray(light_color(rng)) * irradiance * dist**2)}


def spot_light(rng: np.random.Generator, center: np.ndarray, radius: float, max_dist: float,
               irradiance: float) -> dict:
    dist = min(radius * rng.uniform(1.5, 4.0), max_dist)
    pos = center + direction(rng.uniform(0, 360), rng.uniform(30, 85)) * dist
    target = center + rng.normal(size=3) * radius * 0.3
    cutoff = rng.uniform(12, 45)
    return {"type": "spot", "position": vec(pos), "target": vec(target),
            "cutoff_angle": rnd(cutoff, 2), "beam_width": rnd(cutoff * rng.uniform(0.5, 0.95), 2),
            "irradiance": rnd(irradiance),
            "intensity": vec(np.asarray(light_color(rng)) * irradiance * dist**2)}


def random_environment(rng: np.random.Generator, irradiance: float) -> dict:
    """A procedural sky (with or without a sun) or a constant environment."""
    if rng.uniform() < 0.3:
        return {"type": "constant", "irradiance": rnd(irradiance),
                "radiance": vec(np.asarray(light_color(rng)) * irradiance / np.pi)}
    zenith = random_color(rng, saturation=rng.uniform(0.2, 0.8), value=rng.uniform(0.5, 1.0))
    horizon = random_color(rng, saturation=rng.uniform(0.0, 0.4), value=rng.uniform(0.7, 1.0))
    ground = random_color(rng, saturation=rng.uniform(0.0, 0.5), value=rng.uniform(0.1, 0.5))
    sun = None
    if rng.uniform() < 0.6:
        sun = {"azimuth_deg": rnd(rng.uniform(0, 360), 2), "elevation_deg": rnd(rng.uniform(10, 70), 2),
               "size_deg": rnd(rng.uniform(3, 8), 2), "strength": rnd(rng.uniform(1, 6)),
               "color": light_color(rng)}
    strength = sun["strength"] if sun else 0.0
    return {"type": "sky", "zenith": zenith, "horizon": horizon, "ground": ground, "sun": sun,
            "irradiance": rnd(irradiance), "scale": rnd(irradiance / (np.pi * (1.0 + strength)), 6)}


def sky_bitmap(env: dict, size: tuple[int, int] = SKY_SIZE) -> np.ndarray:
    """Latlong (rows: up → down, as Mitsuba's envmap expects with y up) float32 RGB.

    Normalized so that the sky alone gives an upward irradiance of ~pi and the sun adds
    ``strength`` times that, which makes ``scale = irradiance / (pi (1 + strength))``.
    """
    h, w = size
    theta = (np.arange(h) + 0.5) / h * np.pi            # 0 = zenith
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    cos_t = np.cos(th)
    up = np.clip(cos_t, 0, 1)[..., None]
    z, hz, g = (np.asarray(env[k], np.float64) for k in ("zenith", "horizon", "ground"))
    t = (1 - up) ** 3                                    # horizon band
    img = np.where(cos_t[..., None] >= 0, z * (1 - t) + hz * t, g * 0.5 + hz * 0.5 * np.exp(cos_t[..., None] * 8))
    # Normalize: cosine-weighted upper-hemisphere irradiance of the sky = pi.
    dA = np.sin(th) * (np.pi / h) * (2 * np.pi / w)
    lum = img @ np.array([0.2126, 0.7152, 0.0722])
    e = float(np.sum(lum * np.clip(cos_t, 0, None) * dA))
    img = img * (np.pi / max(e, 1e-9))
    sun = env.get("sun")
    if sun and not sun.get("delta"):
        # Mitsuba's latlong: direction (sin t cos p', cos t, sin t sin p') with p' measured like ours
        # up to a fixed offset; the sun only needs to be *somewhere* consistent, so use our convention.
        d = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1)
        s = sun_direction(sun)
        ang = np.arccos(np.clip(d @ s, -1, 1))
        sigma = np.deg2rad(sun["size_deg"]) / 2
        blob = np.exp(-0.5 * (ang / sigma) ** 2)
        e_sun = float(np.sum(blob * np.clip(d @ s, 0, None) * dA))  # irradiance at normal incidence
        img = img + (np.pi * sun["strength"] / max(e_sun, 1e-12)) * blob[..., None] * np.asarray(sun["color"])
    return img.astype(np.float32)


def emitter_dicts(mi, light: dict) -> dict:
    """Mitsuba plugin dict of one light description (area lights are shapes with an area emitter)."""
    T = mi.ScalarTransform4f
    kind = light["type"]
    if kind == "rectangle":
        c, n = np.asarray(light["center"]), np.asarray(light["normal"])
        w, h = light["size"]
        to_world = T().look_at(origin=c.tolist(), target=(c + n).tolist(), up=light["up"]) @ T().scale([w / 2, h / 2, 1])
        return {"type": "rectangle", "to_world": to_world,
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": light["radiance"]}}}
    if kind == "sphere":
        return {"type": "sphere", "center": light["center"], "radius": light["radius"],
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": light["radiance"]}}}
    if kind == "point":
        return {"type": "point", "position": light["position"],
                "intensity": {"type": "rgb", "value": light["intensity"]}}
    if kind == "spot":
        return {"type": "spot", "to_world": T().look_at(origin=light["position"], target=light["target"],
                                                        up=perp_up(np.subtract(light["target"], light["position"]))),
                "cutoff_angle": light["cutoff_angle"], "beam_width": light["beam_width"],
                "intensity": {"type": "rgb", "value": light["intensity"]}}
    raise ValueError(f"unknown light type {kind!r}")


def is_delta_sun(env: dict) -> bool:
    """Whether the sky's sun is a directional light (``sun_dict``) rather than a blob in its map."""
    return env["type"] == "sky" and bool((env.get("sun") or {}).get("delta"))


def sun_direction(sun: dict) -> np.ndarray:
    """Unit vector toward the sun (y up), by the convention of ``sky_bitmap``'s blob."""
    a, el = np.deg2rad(sun["azimuth_deg"]), np.deg2rad(sun["elevation_deg"])
    return np.array([np.cos(el) * np.cos(a), np.sin(el), np.cos(el) * np.sin(a)])


def sun_dict(env: dict) -> dict:
    """Mitsuba's ``directional`` emitter for a delta sun: the irradiance at normal incidence that the blob of
    ``sky_bitmap`` would give (pi x strength x colour, times the map's ``scale``), with no angular size, so
    its shadows are sharp."""
    sun = env["sun"]
    irradiance = np.pi * float(sun["strength"]) * float(env["scale"]) * np.asarray(sun["color"], np.float64)
    return {"type": "directional", "direction": (-sun_direction(sun)).tolist(),
            "irradiance": {"type": "rgb", "value": irradiance.tolist()}}


def environment_dict(mi, env: dict) -> dict:
    if env["type"] == "constant":
        return {"type": "constant", "radiance": {"type": "rgb", "value": env["radiance"]}}
    if env["type"] == "sky":
        return {"type": "envmap", "bitmap": mi.Bitmap(sky_bitmap(env)), "scale": float(env["scale"])}
    raise ValueError(f"unknown environment type {env['type']!r}")
