"""Materials: random BSDF parameters (JSON) → Mitsuba BSDF dicts.

A colour slot holds either an RGB list (linear) or ``{"texture": <render.textures params>}``; the
texture is regenerated from its parameters at build time. Families are the ones named in
``SceneConfig.materials`` and map one-to-one onto Mitsuba plugins.
"""
from __future__ import annotations

import json

import numpy as np

from mcdenoise.render.rounding import rnd
from mcdenoise.render.textures import make_texture, random_color, random_texture_params

FAMILIES = ("principled", "diffuse", "plastic", "roughplastic", "conductor", "roughconductor",
            "dielectric", "roughdielectric")
CONDUCTORS = ("Au", "Ag", "Al", "Cu", "Cr", "W", "Ir", "Rh")
TRANSMISSIVE = ("dielectric", "roughdielectric")


def random_color_or_texture(rng: np.random.Generator, texture_probability: float) -> list | dict:
    if rng.uniform() < texture_probability:
        return {"texture": random_texture_params(rng)}
    return random_color(rng)


def pick_family(rng: np.random.Generator, weights: dict) -> str:
    unknown = sorted(set(weights) - set(FAMILIES))
    if unknown:
        raise ValueError(f"unknown material family {unknown[0]!r} (known: {', '.join(FAMILIES)})")
    names = [n for n in FAMILIES if float(weights.get(n, 0.0)) > 0]
    if not names:
        raise ValueError("scene.materials: every weight is zero")
    w = np.array([float(weights[n]) for n in names])
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def random_material(rng: np.random.Generator, family: str, texture_probability: float) -> dict:
    """Random parameters of one material of the given family."""
    u = lambda a, b: rnd(rng.uniform(a, b))  # noqa: E731
    color = lambda: random_color_or_texture(rng, texture_probability)  # noqa: E731
    if family == "principled":
        m = {"family": family, "base_color": color(), "roughness": u(0.05, 1.0),
             "metallic": u(0.3, 1.0) if rng.uniform() < 0.35 else 0.0,
             "specular": u(0.2, 0.8),
             "spec_trans": u(0.5, 1.0) if rng.uniform() < 0.12 else 0.0}
        if rng.uniform() < 0.2:
            m["clearcoat"], m["clearcoat_gloss"] = u(0.3, 1.0), u(0.3, 1.0)
        if rng.uniform() < 0.1:
            m["sheen"] = u(0.2, 1.0)
        if rng.uniform() < 0.1:
            m["anisotropic"] = u(0.2, 0.9)
        return m
    if family == "diffuse":
        return {"family": family, "reflectance": color()}
    if family == "plastic":
        return {"family": family, "diffuse_reflectance": color(), "int_ior": u(1.4, 1.7),
                "nonlinear": bool(rng.uniform() < 0.5)}
    if family == "roughplastic":
        return {"family": family, "diffuse_reflectance": color(), "int_ior": u(1.4, 1.7),
                "alpha": u(0.03, 0.5), "distribution": "ggx" if rng.uniform() < 0.5 else "beckmann",
                "nonlinear": bool(rng.uniform() < 0.5)}
    if family in ("conductor", "roughconductor"):
        m = {"family": family, "material": CONDUCTORS[int(rng.integers(len(CONDUCTORS)))]}
        if rng.uniform() < 0.25:  # a tinted or patterned metal
            m["specular_reflectance"] = random_color_or_texture(rng, texture_probability)
        if family == "roughconductor":
            m["alpha"] = u(0.02, 0.5)
            m["distribution"] = "ggx" if rng.uniform() < 0.7 else "beckmann"
        return m
    if family in TRANSMISSIVE:
        m = {"family": family, "int_ior": u(1.33, 1.9), "ext_ior": 1.000277}
        if rng.uniform() < 0.3:  # coloured glass
            m["specular_transmittance"] = random_color(rng, value=rng.uniform(0.7, 1.0))
        if family == "roughdielectric":
            m["alpha"] = u(0.02, 0.35)
            m["distribution"] = "ggx" if rng.uniform() < 0.7 else "beckmann"
        return m
    raise ValueError(f"unknown material family {family!r} (known: {', '.join(FAMILIES)})")


def is_transmissive(mat: dict) -> bool:
    return mat["family"] in TRANSMISSIVE or float(mat.get("spec_trans", 0.0)) > 0


class TextureCache:
    """Bitmaps of one build, keyed by their parameters (the same texture is made once)."""

    def __init__(self, mi):
        self.mi = mi
        self._bitmaps: dict = {}

    def texture(self, params: dict) -> dict:
        key = json.dumps(params, sort_keys=True)
        if key not in self._bitmaps:
            self._bitmaps[key] = self.mi.Bitmap(make_texture(params))
        uv = float(params.get("uv_scale", 1.0))
        return {"type": "bitmap", "bitmap": self._bitmaps[key], "filter_type": "bilinear",
                "wrap_mode": "repeat", "to_uv": self.mi.ScalarTransform4f().scale([uv, uv, 1.0])}


def _slot(value, tex: TextureCache):
    if isinstance(value, dict):
        return tex.texture(value["texture"])
    return {"type": "rgb", "value": [float(c) for c in value]}


COLOR_SLOTS = ("base_color", "reflectance", "diffuse_reflectance", "specular_reflectance", "specular_transmittance")


def bsdf_dict(mat: dict, tex: TextureCache, two_sided: bool = False) -> dict:
    """The Mitsuba plugin dict of a material description.

    ``two_sided`` wraps opaque BSDFs in ``twosided`` (for open or inconsistently wound meshes, whose
    back faces would otherwise render black); transmissive ones already handle both sides.
    """
    d = {"type": mat["family"]}
    for key, value in mat.items():
        if key == "family":
            continue
        d[key] = _slot(value, tex) if key in COLOR_SLOTS else value
    if two_sided and not is_transmissive(mat):
        return {"type": "twosided", "bsdf": d}
    return d
