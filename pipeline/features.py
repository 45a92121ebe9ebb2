"""The input features of every network: how each buffer of the schema is normalised, in one table.

``TABLE`` lists the channel groups in order, each ``(key, channels, kind)``, derived from
``pipeline.schema.BUFFERS``: every buffer in schema order, then one relative-variance channel
per buffer. How a kind is encoded:

- ``radiance`` (``color`` and the five components of the exact decomposition): a model-specific
  map (``Encoding.radiance``): the cleaner and the Isik/AFGSA networks take ``log1p(max(x, 0))``
  (``log1p_radiance``), the diffusion model its [−1, 1] model space;
- ``normal``: as stored (world space, in [−1, 1]) or, with ``Encoding.normals01``, rotated into
  camera space when a rotation is given, clipped to [−1, 1] and mapped to [0, 1] by (n + 1)/2;
- ``depth``: divided by the frame's largest depth (background 0 stays 0; ``depth_feature``):
  scenes differ in scale, and the networks need relative depth edges, not metres;
- ``identity`` (``albedo``, ``roughness``, ``metallic``, ``transmission``): as stored, in [0, 1];
- ``relative_variance``: ``1 + log10(rel + 1e-6) / 6`` of the relative variance
  ``rel = v̄ / (m̄² + 1e-2)`` (v̄, m̄: means over the buffer's channels of variance and value;
  ``relative_variance_feature``). Relative variance (squared coefficient of variation) says how
  noisy a pixel is independently of its brightness; the 1e-2 makes dark pixels count absolutely.
  The log scale matters: a 1024-spp ground truth has rel ~ 1e-5 … 1e-2 and a 4-spp stack
  ~ 0.1 … 10, so ``log1p(rel)`` (tried first) was ~0 for every ground-truth pixel; the log maps
  1e-6 → 0, 1e-3 → 0.5, 1 → 1.

With ``Encoding.spp`` a last channel holds the sample count, a constant log2(spp)/6 (1 at 64 spp),
so one model can serve any spp. A buffer missing from the input (a feature a scene or a reader
left out) is its documented background value before the encoding, so the channel count never
depends on the scene.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import schema

# Relative-variance floor (radiance² units) and the log scale's zero, see the module docstring.
VARIANCE_FLOOR = 1e-2
RELATIVE_VARIANCE_MIN = 1e-6


def _kind(buf: schema.Buffer) -> str:
    if buf.radiance:
        return "radiance"
    return buf.name if buf.name in ("normal", "depth") else "identity"


# (key, channels, kind) of every input channel group, in order.
TABLE: tuple[tuple[str, int, str], ...] = (
    tuple((b.name, b.size, _kind(b)) for b in schema.BUFFERS)
    + tuple((schema.variance_name(b.name), 1, "relative_variance") for b in schema.BUFFERS)
)


def log1p_radiance(x: np.ndarray) -> np.ndarray:
    """``log1p(max(x, 0))``: HDR radiance spans 0 … 1e5; the log keeps a conv net's inputs in a few
    units (1e5 → 11.5) while staying linear near 0."""
    return np.log1p(np.maximum(x, 0.0))


@dataclass(frozen=True)
class Encoding:
    """The model-specific choices of the table's encoding (see the module docstring)."""
    radiance: Callable[[np.ndarray], np.ndarray] = log1p_radiance
    normals01: bool = False   # camera space (given a rotation) mapped to [0, 1]; False: as stored
    spp: bool = False         # append the log2(spp)/6 channel


def names(encoding: Encoding = Encoding()) -> list[str]:
    """One name per channel, e.g. ``color.R``, ``normal.X``, ``depth.variance``, ``spp``."""
    out = []
    for key, _, kind in TABLE:
        out += [key] if kind == "relative_variance" else [f"{key}.{c}" for c in schema.BY_NAME[key].channels]
    return out + (["spp"] if encoding.spp else [])


def relative_variance_feature(variance: np.ndarray, mean_square: np.ndarray) -> np.ndarray:
    """``1 + log10(v / (m² + 1e-2) + 1e-6) / 6``: 0 for a noise-free pixel, ~1 for relative variance 1."""
    rel = np.maximum(variance, 0.0) / (mean_square + VARIANCE_FLOOR)
    return (1.0 + np.log10(rel + RELATIVE_VARIANCE_MIN) / 6.0).astype(np.float32)


def variance_feature(buffers: dict[str, np.ndarray], name: str, shape: tuple[int, int]) -> np.ndarray:
    """(1, H, W) ``relative_variance_feature`` of buffer ``name`` from its channel means; zeros where
    the buffer or its variance is missing."""
    v, m = buffers.get(schema.variance_name(name)), buffers.get(name)
    if v is None or m is None:
        return np.zeros((1, *shape), np.float32)
    return relative_variance_feature(v.astype(np.float32).mean(axis=2), (m.astype(np.float32) ** 2).mean(axis=2))[None]


def depth_feature(depth: np.ndarray) -> np.ndarray:
    """Depth divided by the frame's largest depth (background 0 stays 0; all zeros if nothing is in front)."""
    top = float(depth.max()) if depth.size else 0.0
    return depth / top if top > 0 else np.zeros_like(depth)


def _group(x: np.ndarray, kind: str, encoding: Encoding, rotation: np.ndarray | None) -> np.ndarray:
    """One buffer (H, W, C) float32 encoded as its ``kind`` says."""
    if kind == "radiance":
        return encoding.radiance(x)
    if kind == "normal" and encoding.normals01:
        if rotation is not None:
            x = x @ rotation.T
        return (np.clip(x, -1.0, 1.0) + 1.0) / 2.0
    if kind == "depth":
        return depth_feature(x)
    return x


def encode(buffers: dict[str, np.ndarray], encoding: Encoding = Encoding(), spp: int | None = None,
           rotation: np.ndarray | None = None) -> np.ndarray:
    """The (C, H, W) float32 features of one image's buffers (H, W, C arrays; ``color`` required).
    ``rotation``: 3×3 world→camera rotation of the normals (``normals01``); ``spp``: with ``Encoding.spp``."""
    H, W = buffers["color"].shape[:2]
    parts = []
    for key, n, kind in TABLE:
        if kind == "relative_variance":
            parts.append(variance_feature(buffers, key.removesuffix(".variance"), (H, W)))
            continue
        x = buffers.get(key)
        x = np.full((H, W, n), schema.BY_NAME[key].background, np.float32) if x is None else x.astype(np.float32)
        parts.append(np.moveaxis(_group(x, kind, encoding, rotation), 2, 0))
    if encoding.spp:
        parts.append(np.full((1, H, W), math.log2(max(int(spp), 1)) / 6.0, np.float32))
    return np.ascontiguousarray(np.concatenate(parts, axis=0), dtype=np.float32)
