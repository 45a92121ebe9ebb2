"""Materials of furnished rooms and product shots: wood, fabric, plaster, tile, metal, glass, glazed ceramic,
as material descriptions (render.materials) drawn from palettes that look like real ones (browns for wood,
muted walls, green leaves) rather than from the whole colour wheel."""
from __future__ import annotations

from mcdenoise.render.rounding import rnd
from mcdenoise.render.textures import hsv_color, random_texture_params, surface_texture_params


def tone(rng, hue, sat, val) -> list:
    """A linear colour with hue, saturation and value drawn from the given (lo, hi) ranges (sRGB HSV)."""
    return hsv_color(rng.uniform(*hue) % 1.0, rng.uniform(*sat), rng.uniform(*val))


def wood(rng, uv_scale: float = 1.0, gloss: float | None = None) -> dict:
    """Planked or grained wood (a principled or plastic coat over a wood texture); ``gloss``: its roughness."""
    dark = rng.uniform(0.2, 0.6)
    hue = (0.04, 0.11)
    colors = [tone(rng, hue, (0.45, 0.75), (dark * 0.6, dark * 0.8)), tone(rng, hue, (0.4, 0.7), (dark, dark * 1.2)),
              tone(rng, hue, (0.3, 0.6), (min(0.95, dark * 1.4), min(0.98, dark * 1.6)))]
    tex = {"texture": surface_texture_params(rng, "wood", colors, int(rng.integers(3, 9)), uv_scale)}
    rough = rnd(rng.uniform(0.25, 0.7) if gloss is None else gloss)
    if rng.uniform() < 0.5:
        return {"family": "principled", "base_color": tex, "roughness": rough, "metallic": 0.0, "specular": 0.5}
    return {"family": "roughplastic", "diffuse_reflectance": tex, "int_ior": 1.5, "alpha": rnd(max(rough**2, 0.005)),
            "distribution": "ggx", "nonlinear": False}


def fabric(rng, uv_scale: float = 8.0) -> dict:
    base = tone(rng, (0, 1), (0.1, 0.6), (0.2, 0.8))
    if rng.uniform() < 0.6:
        colors = [[rnd(c * 0.7) for c in base], base]
        return {"family": "diffuse", "reflectance": {"texture": surface_texture_params(rng, "fabric", colors, 16, uv_scale)}}
    return {"family": "principled", "base_color": base, "roughness": rnd(rng.uniform(0.6, 1.0)), "metallic": 0.0,
            "specular": 0.3, "sheen": rnd(rng.uniform(0.3, 1.0))}


def plaster(rng) -> dict:
    base = tone(rng, (0, 1), (0.0, 0.25), (0.55, 0.95))
    colors = [[rnd(c * 0.9) for c in base], base]
    return {"family": "diffuse", "reflectance": {"texture": surface_texture_params(rng, "plaster", colors, 4, 0.4)}}


def tile(rng, polished: bool) -> dict:
    base = tone(rng, (0, 1), (0.0, 0.4), (0.3, 0.9))
    colors = [base, [rnd(c * 0.8) for c in base], tone(rng, (0, 1), (0.0, 0.1), (0.5, 0.8))]
    tex = {"texture": surface_texture_params(rng, "tile", colors, int(rng.integers(2, 6)), 0.5)}
    return {"family": "roughplastic", "diffuse_reflectance": tex, "int_ior": 1.5,
            "alpha": rnd(rng.uniform(0.005, 0.04) if polished else rng.uniform(0.1, 0.4)),
            "distribution": "ggx", "nonlinear": False}


def floor(rng, polished_probability: float) -> dict:
    """Wood or tile, polished (sharp reflections of the room) with ``polished_probability``."""
    polished = bool(rng.uniform() < polished_probability)
    if rng.uniform() < 0.6:
        return wood(rng, 0.5, rnd(rng.uniform(0.03, 0.12)) if polished else None)
    return tile(rng, polished)


def matte(rng, hue=(0, 1), sat=(0.0, 0.6), val=(0.1, 0.8)) -> dict:
    return {"family": "diffuse", "reflectance": tone(rng, hue, sat, val)}


def metal(rng, rough: tuple = (0.02, 0.3)) -> dict:
    kind = ("Al", "Cr", "Cu", "Au", "Ag")[int(rng.integers(5))]
    return {"family": "roughconductor", "material": kind, "alpha": rnd(rng.uniform(*rough)), "distribution": "ggx"}


def glass(rng, rough_probability: float = 0.2) -> dict:
    m = {"family": "dielectric", "int_ior": rnd(rng.uniform(1.45, 1.55)), "ext_ior": 1.000277}
    if rng.uniform() < 0.4:   # green, brown or blue bottle glass
        m["specular_transmittance"] = tone(rng, (0.08, 0.6), (0.3, 0.8), (0.6, 0.95))
    if rng.uniform() < rough_probability:
        m.update(family="roughdielectric", alpha=rnd(rng.uniform(0.03, 0.2)), distribution="ggx")
    return m


def glazed(rng, rough: tuple = (0.01, 0.2)) -> dict:
    """Glazed ceramic or lacquer: a coloured base under a smooth clear coat."""
    return {"family": "roughplastic", "diffuse_reflectance": tone(rng, (0, 1), (0.0, 0.8), (0.1, 0.9)), "int_ior": 1.5,
            "alpha": rnd(rng.uniform(*rough)), "distribution": "ggx", "nonlinear": False}


def art(rng) -> dict:
    tex = random_texture_params(rng, size=128)
    tex["uv_scale"] = rnd(rng.uniform(0.8, 3.0))
    return {"family": "diffuse", "reflectance": {"texture": tex}}


def room_palette(rng, polished_probability: float) -> dict:
    """A material for every role of render.furniture's items and of the room's surfaces."""
    return {
        "wood": wood(rng), "fabric": fabric(rng), "cushion": fabric(rng), "linen": matte(rng, sat=(0, 0.1), val=(0.7, 0.9)),
        "metal": metal(rng), "dark": matte(rng, sat=(0, 0.3), val=(0.03, 0.12)), "ceramic": glazed(rng),
        "glass": glass(rng), "accent": glazed(rng, (0.05, 0.4)),
        "book_a": matte(rng, val=(0.15, 0.7)), "book_b": matte(rng, val=(0.15, 0.7)), "book_c": matte(rng, val=(0.15, 0.7)),
        "frame": wood(rng) if rng.uniform() < 0.6 else metal(rng), "art": art(rng), "rug": fabric(rng, 3.0),
        "leaf": matte(rng, hue=(0.2, 0.38), sat=(0.4, 0.8), val=(0.2, 0.55)),
        "shade": matte(rng, hue=(0.05, 0.15), sat=(0.0, 0.3), val=(0.75, 0.95)),
        "wall": plaster(rng), "ceiling": matte(rng, sat=(0, 0.05), val=(0.8, 0.92)),
        "floor": floor(rng, polished_probability), "trim": matte(rng, sat=(0, 0.05), val=(0.75, 0.9)),
        "outside": matte(rng, hue=(0.15, 0.35), sat=(0.2, 0.6), val=(0.15, 0.4)),
    }
