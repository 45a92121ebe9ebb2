"""Procedural textures: pure numpy functions from a small parameter dict to an (H, W, 3) float32 image.

The scene description stores only the parameters (kind, seed, colours, scale), never pixels, so a
texture is regenerated bit-identically wherever the scene is built. Values are linear RGB in [0, 1]
(palettes are picked in sRGB, where "pleasant" colours are easy to describe, and converted to linear
because Mitsuba treats float bitmaps as linear).
"""
from __future__ import annotations

import numpy as np

from mcdenoise.pipeline.metrics import srgb_to_linear

KINDS = ("checker", "stripes", "noise", "cells", "dots", "gradient")
DEFAULT_SIZE = 256


def random_color(rng: np.random.Generator, saturation: float | None = None, value: float | None = None) -> list:
    """A linear-RGB colour from a random hue/saturation/value (sRGB space), as a plain list."""
    h = rng.uniform()
    s = rng.uniform(0.1, 0.9) if saturation is None else saturation
    v = rng.uniform(0.25, 0.95) if value is None else value
    return hsv_color(h, s, v)


def hsv_color(h: float, s: float, v: float) -> list:
    """The linear-RGB colour of an sRGB hue/saturation/value (all in [0, 1]), as a plain list."""
    i, f = int(h * 6) % 6, h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    rgb = [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]
    return [round(float(x), 4) for x in srgb_to_linear(np.asarray(rgb, dtype=np.float64))]


def random_texture_params(rng: np.random.Generator, size: int = DEFAULT_SIZE) -> dict:
    """Parameters of a random procedural texture (JSON-serializable)."""
    kind = KINDS[int(rng.integers(len(KINDS)))]
    n_colors = 2 if kind in ("checker", "stripes", "dots", "gradient") else int(rng.integers(2, 5))
    return {
        "kind": kind,
        "seed": int(rng.integers(2**31)),
        "size": int(size),
        "colors": [random_color(rng) for _ in range(n_colors)],
        # Repetitions of the pattern across the texture (and the texture repeats over UV space).
        "frequency": round(float(rng.uniform(2.0, 8.0)), 3),
        "angle_deg": round(float(rng.uniform(0.0, 180.0)), 2),
        "uv_scale": round(float(rng.uniform(0.3, 1.5)), 3),
    }


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    # Pixel-centre coordinates in [0, 1).
    c = (np.arange(size, dtype=np.float64) + 0.5) / size
    return np.meshgrid(c, c, indexing="xy")  # x varies along columns


def _mix(colors: list, t: np.ndarray) -> np.ndarray:
    """Piecewise-linear palette lookup, t in [0, 1]."""
    pal = np.asarray(colors, dtype=np.float64)
    if len(pal) == 1:
        return np.broadcast_to(pal[0], t.shape + (3,)).copy()
    x = np.clip(t, 0, 1) * (len(pal) - 1)
    i = np.minimum(np.floor(x).astype(int), len(pal) - 2)
    f = (x - i)[..., None]
    return pal[i] * (1 - f) + pal[i + 1] * f


def _smooth(t):
    return t * t * (3 - 2 * t)


def value_noise(size: int, seed: int, frequency: float, octaves: int = 4) -> np.ndarray:
    """Tileable fractal value noise in [0, 1]: random lattice values, smoothstep-interpolated."""
    rng = np.random.default_rng(seed)
    x, y = _grid(size)
    out = np.zeros((size, size))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        n = max(2, int(round(frequency * 2**o)))
        lattice = rng.uniform(size=(n, n))
        gx, gy = x * n, y * n
        ix, iy = np.floor(gx).astype(int), np.floor(gy).astype(int)
        fx, fy = _smooth(gx - ix), _smooth(gy - iy)
        x0, y0, x1, y1 = ix % n, iy % n, (ix + 1) % n, (iy + 1) % n  # wrap: the texture tiles
        a = lattice[y0, x0] * (1 - fx) + lattice[y0, x1] * fx
        b = lattice[y1, x0] * (1 - fx) + lattice[y1, x1] * fx
        out += amp * (a * (1 - fy) + b * fy)
        total += amp
        amp *= 0.5
    out /= total
    lo, hi = out.min(), out.max()
    return (out - lo) / max(hi - lo, 1e-9)


def cells(size: int, seed: int, frequency: float) -> tuple[np.ndarray, np.ndarray]:
    """Tileable Voronoi cells: (cell id in [0, 1), distance to the nearest border-ish edge in [0, 1])."""
    rng = np.random.default_rng(seed)
    n = max(2, int(round(frequency / 2)))  # n*n sites; kept small because the loop is per site
    pts = rng.uniform(size=(n * n, 2))
    ids = rng.uniform(size=n * n)
    x, y = _grid(size)
    d1 = np.full((size, size), np.inf)
    d2 = np.full((size, size), np.inf)
    best = np.zeros((size, size))
    for k, (px, py) in enumerate(pts):
        dx = np.abs(x - px)
        dy = np.abs(y - py)
        d = np.hypot(np.minimum(dx, 1 - dx), np.minimum(dy, 1 - dy))  # toroidal distance: tiles
        closer = d < d1
        d2 = np.where(closer, d1, np.minimum(d2, d))
        best = np.where(closer, ids[k], best)
        d1 = np.where(closer, d, d1)
    edge = np.clip((d2 - d1) * n * 2, 0, 1)
    return best, edge


def make_texture(p: dict) -> np.ndarray:
    """(size, size, 3) float32 linear RGB in [0, 1] from parameters made by random_texture_params."""
    size, kind, seed = int(p.get("size", DEFAULT_SIZE)), p["kind"], int(p["seed"])
    colors, freq = p["colors"], float(p.get("frequency", 4.0))
    x, y = _grid(size)
    a = np.deg2rad(float(p.get("angle_deg", 0.0)))
    if kind == "checker":
        # Integer frequency keeps the pattern tileable.
        n = max(1, int(round(freq)))
        t = ((np.floor(x * n) + np.floor(y * n)) % 2).astype(np.float64)
    elif kind == "stripes":
        # Integer wave numbers along x and y keep the stripes tileable at any angle.
        kx, ky = int(round(freq * np.cos(a))), int(round(freq * np.sin(a)))
        if kx == 0 and ky == 0:
            kx = 1
        s = np.sin(2 * np.pi * (kx * x + ky * y))
        t = 0.5 + 0.5 * np.tanh(4.0 * s)  # soft edges: less aliasing than a hard step
    elif kind == "noise":
        t = value_noise(size, seed, freq / 2)
    elif kind == "cells":
        cid, edge = cells(size, seed, freq)
        img = _mix(colors, cid) * (0.35 + 0.65 * edge[..., None])
        return np.clip(img, 0, 1).astype(np.float32)
    elif kind == "dots":
        n = max(1, int(round(freq)))
        fx, fy = (x * n) % 1 - 0.5, (y * n) % 1 - 0.5
        r = np.hypot(fx, fy)
        t = np.clip((0.3 - r) * size / n * 0.5, 0, 1)
    elif kind == "gradient":
        t = 0.5 + 0.5 * np.sin(2 * np.pi * (np.cos(a) * x + np.sin(a) * y) + 2 * np.pi * value_noise(size, seed, 2, 2))
    elif kind in SURFACE_KINDS:
        return np.clip(SURFACES[kind](p, x, y), 0, 1).astype(np.float32)
    else:
        raise ValueError(f"unknown texture kind {kind!r} (known: {', '.join(KINDS + SURFACE_KINDS)})")
    return np.clip(_mix(colors, t), 0, 1).astype(np.float32)


def surface_texture_params(rng: np.random.Generator, kind: str, colors: list, frequency: float,
                           uv_scale: float, size: int = DEFAULT_SIZE) -> dict:
    """Parameters of a wood, tile, fabric or plaster texture in the given palette (JSON-serializable);
    ``frequency``: planks, tiles or threads across the texture."""
    if kind not in SURFACE_KINDS:
        raise ValueError(f"unknown surface texture {kind!r} (known: {', '.join(SURFACE_KINDS)})")
    return {"kind": kind, "seed": int(rng.integers(2**31)), "size": int(size), "colors": colors,
            "frequency": round(float(frequency), 3), "angle_deg": 0.0, "uv_scale": round(float(uv_scale), 4)}


def _lattice(size: int, rng: np.random.Generator, nx: int, ny: int) -> np.ndarray:
    """One octave of tileable value noise with nx × ny lattice cells (stretched when they differ)."""
    x, y = _grid(size)
    lattice = rng.uniform(size=(ny, nx))
    gx, gy = x * nx, y * ny
    ix, iy = np.floor(gx).astype(int), np.floor(gy).astype(int)
    fx, fy = _smooth(gx - ix), _smooth(gy - iy)
    a = lattice[iy % ny, ix % nx] * (1 - fx) + lattice[iy % ny, (ix + 1) % nx] * fx
    b = lattice[(iy + 1) % ny, ix % nx] * (1 - fx) + lattice[(iy + 1) % ny, (ix + 1) % nx] * fx
    return a * (1 - fy) + b * fy


def _wood(p: dict, x, y) -> np.ndarray:
    # Planks along x: each its own tone and grain offset, long streaks of grain, dark seams between them.
    rng = np.random.default_rng(int(p["seed"]))
    n = max(1, int(round(float(p["frequency"]))))
    row = np.floor(y * n).astype(int) % n
    tone = rng.uniform(0.0, 1.0, n)[row]
    grain = _lattice(len(x), rng, 2, 8 * n) * 0.6 + _lattice(len(x), rng, 4, 32 * n) * 0.4
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (grain * 6 + rng.uniform(0, 1, n)[row]))
    t = np.clip(0.55 * tone + 0.45 * rings, 0, 1)
    seam = np.abs((y * n) % 1 - 0.5) > 0.47
    return _mix(p["colors"], t) * np.where(seam, 0.45, 1.0)[..., None]


def _tile(p: dict, x, y) -> np.ndarray:
    # Square tiles, each a shade of the palette, in light grout lines.
    rng = np.random.default_rng(int(p["seed"]))
    n = max(1, int(round(float(p["frequency"]))))
    ix, iy = np.floor(x * n).astype(int) % n, np.floor(y * n).astype(int) % n
    shade = rng.uniform(0, 1, (n, n))[iy, ix] * 0.8 + 0.2 * _lattice(len(x), rng, 4 * n, 4 * n)
    pal = p["colors"][:-1] if len(p["colors"]) > 2 else p["colors"]
    grout = (np.abs((x * n) % 1 - 0.5) > 0.46) | (np.abs((y * n) % 1 - 0.5) > 0.46)
    return np.where(grout[..., None], np.asarray(p["colors"][-1], float), _mix(pal, shade))


def _fabric(p: dict, x, y) -> np.ndarray:
    # A plain weave: warp and weft threads alternating over and under, with slow unevenness of the dye.
    rng = np.random.default_rng(int(p["seed"]))
    n = max(2, int(round(float(p["frequency"]))))
    over = (np.floor(x * n) + np.floor(y * n)) % 2
    across = np.where(over > 0, np.sin(np.pi * ((x * n) % 1)), np.sin(np.pi * ((y * n) % 1)))
    t = 0.6 * across + 0.4 * _lattice(len(x), rng, 6, 6)
    return _mix(p["colors"], t)


def _plaster(p: dict, x, y) -> np.ndarray:
    # Painted plaster: a flat colour with soft, low-contrast blotches.
    t = value_noise(len(x), int(p["seed"]), max(2.0, float(p["frequency"])), octaves=5)
    return _mix(p["colors"], 0.5 + 0.5 * (t - 0.5))


SURFACES = {"wood": _wood, "tile": _tile, "fabric": _fabric, "plaster": _plaster}
# Surfaces of furnished rooms (render.interior); apart from KINDS, which random_texture_params draws by index.
SURFACE_KINDS = tuple(SURFACES)
