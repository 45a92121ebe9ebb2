"""The channel schema: every buffer the renderer produces, its EXR channel names and storage type.

One place for the names. The integrator, the store, the cleaner, the trainer and the evaluator
all refer to buffers by ``Buffer.name`` and get EXR channel names from here.

EXR naming follows compositing conventions so that ``oiiotool --info -v`` and Nuke read a frame
as expected: the beauty is ``R,G,B``; other layers are ``<layer>.<channel>``; normals are
``N.X/Y/Z``; the variance of a layer is the sub-layer ``<layer>.variance`` (the beauty's is
``variance.R/G/B``).

Variance convention: ``<layer>.variance`` is the variance of the *pixel estimate* (the sample
mean over the image's spp samples), i.e. the unbiased per-sample variance divided by spp. It
is what a denoiser needs as a noise level and what combines across stacks
(``pipeline.store.combine_stacks``).

The radiance decomposition is exact: ``color = emission + diffuse_direct + specular_direct +
diffuse_indirect + specular_indirect`` per sample, hence per pixel.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class Buffer:
    name: str                 # our name, used everywhere in code
    layer: str                # EXR layer ("" for the beauty)
    channels: tuple[str, ...]  # EXR channel suffixes
    dtype: type               # storage type of the mean (variances are always float32)
    radiance: bool            # part of the radiance decomposition (HDR, float32)
    doc: str
    background: float = 0.0   # value where the camera ray escapes (documented in docs/store.md)

    @property
    def exr_channels(self) -> tuple[str, ...]:
        return tuple(f"{self.layer}.{c}" if self.layer else c for c in self.channels)

    @property
    def variance_channels(self) -> tuple[str, ...]:
        base = f"{self.layer}.variance" if self.layer else "variance"
        return tuple(f"{base}.{c}" for c in self.channels)

    @property
    def size(self) -> int:
        return len(self.channels)


RGB = ("R", "G", "B")

BUFFERS: tuple[Buffer, ...] = (
    Buffer("color", "", RGB, np.float32, True, "Total radiance (the beauty)."),
    Buffer("emission", "emission", RGB, np.float32, True,
           "Emission seen directly by the camera ray (area lights, environment); also the 'emissive' feature."),
    Buffer("diffuse_direct", "diffuse_direct", RGB, np.float32, True,
           "Light arriving at the first hit from an emitter (NEE + MIS-weighted BSDF hit), through the diffuse lobe."),
    Buffer("specular_direct", "specular_direct", RGB, np.float32, True,
           "As diffuse_direct, through the glossy/specular lobes (including transmission)."),
    Buffer("diffuse_indirect", "diffuse_indirect", RGB, np.float32, True,
           "Light of path length >= 3 whose first bounce sampled the diffuse lobe."),
    Buffer("specular_indirect", "specular_indirect", RGB, np.float32, True,
           "Light of path length >= 3 whose first bounce sampled a glossy/specular lobe."),
    Buffer("albedo", "albedo", RGB, np.float16, False,
           "Reflectance at the first hit: diffuse reflectance; 1 for purely specular materials; 0 for background."),
    Buffer("normal", "N", ("X", "Y", "Z"), np.float16, False, "World-space shading normal at the first hit, 0 for background."),
    Buffer("depth", "depth", ("Z",), np.float32, False,
           "Camera-space z (distance along the view axis) of the first hit; 0 for background."),
    Buffer("roughness", "roughness", ("Y",), np.float16, False,
           "Perceptual roughness in [0, 1] at the first hit (diffuse: 1, smooth: 0, rough: sqrt(GGX alpha))."),
    Buffer("metallic", "metallic", ("Y",), np.float16, False,
           "Metallic in [0, 1] at the first hit (conductors: 1, principled: its 'metallic')."),
    Buffer("transmission", "transmission", ("Y",), np.float16, False,
           "Specular transmission in [0, 1] at the first hit (dielectrics: 1, principled: 'spec_trans')."),
)

BY_NAME: dict[str, Buffer] = {b.name: b for b in BUFFERS}
RADIANCE_COMPONENTS: tuple[str, ...] = ("emission", "diffuse_direct", "specular_direct",
                                        "diffuse_indirect", "specular_indirect")
# Features the integrator can skip when the scene's materials cannot produce them.
OPTIONAL_FEATURES: tuple[str, ...] = ("emission", "roughness", "metallic", "transmission")


def variance_name(name: str) -> str:
    """Key under which the variance of buffer ``name`` appears in a buffer dictionary."""
    return f"{name}.variance"


def exr_channel_map() -> dict[str, tuple[str, int, bool]]:
    """EXR channel name → (buffer name, channel index, is_variance)."""
    out = {}
    for b in BUFFERS:
        for i, ch in enumerate(b.exr_channels):
            out[ch] = (b.name, i, False)
        for i, ch in enumerate(b.variance_channels):
            out[ch] = (b.name, i, True)
    return out


def beauty_from_components(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """The beauty as the sum of the radiance components (HxWx3 float32 arrays in ``arrays``).

    Summed in float64 in ``RADIANCE_COMPONENTS`` order and rounded once to float32, so the result
    is a deterministic function of the stored components: the compact encoding
    (``pipeline.exr``, docs/store.md) stores the components and derives the beauty with this.
    """
    total = np.zeros(arrays[RADIANCE_COMPONENTS[0]].shape, np.float64)
    for name in RADIANCE_COMPONENTS:
        total += arrays[name]
    return total.astype(np.float32)


def storage_dtype(exr_channel: str) -> type:
    buf, _, is_var = exr_channel_map()[exr_channel]
    return np.float32 if is_var else BY_NAME[buf].dtype


# Layers a denoiser writes beside the schema's buffers (float32 R, G, B each): ``std``, the per-pixel
# standard deviation of the samples whose mean is the denoised colour (``denoise --samples K``).
OUTPUT_LAYERS = ("std",)


def output_layer_channels() -> dict[str, type]:
    return {f"{layer}.{c}": np.float32 for layer in OUTPUT_LAYERS for c in "RGB"}


# ---- Features: the buffers as network input channels ---------------------------------------------
# The input features of every network: how each buffer of the schema is normalised, in one table.
#
# ``TABLE`` lists the channel groups in order, each ``(key, channels, kind)``, derived from
# ``pipeline.schema.BUFFERS``: every buffer in schema order, then one relative-variance channel
# per buffer. How a kind is encoded:
#
# - ``radiance`` (``color`` and the five components of the exact decomposition): a model-specific
#   map (``Encoding.radiance``): the cleaner and the Isik/AFGSA networks take ``log1p(max(x, 0))``
#   (``log1p_radiance``), the diffusion model its [−1, 1] model space;
# - ``normal``: as stored (world space, in [−1, 1]) or, with ``Encoding.normals01``, rotated into
#   camera space when a rotation is given, clipped to [−1, 1] and mapped to [0, 1] by (n + 1)/2;
# - ``depth``: divided by the frame's largest depth (background 0 stays 0; ``depth_feature``):
#   scenes differ in scale, and the networks need relative depth edges, not metres;
# - ``identity`` (``albedo``, ``roughness``, ``metallic``, ``transmission``): as stored, in [0, 1];
# - ``relative_variance``: ``1 + log10(rel + 1e-6) / 6`` of the relative variance
#   ``rel = v̄ / (m̄² + 1e-2)`` (v̄, m̄: means over the buffer's channels of variance and value;
#   ``relative_variance_feature``). Relative variance (squared coefficient of variation) says how
#   noisy a pixel is independently of its brightness; the 1e-2 makes dark pixels count absolutely.
#   The log scale matters: a 1024-spp ground truth has rel ~ 1e-5 … 1e-2 and a 4-spp stack
#   ~ 0.1 … 10, so ``log1p(rel)`` (tried first) was ~0 for every ground-truth pixel; the log maps
#   1e-6 → 0, 1e-3 → 0.5, 1 → 1.
#
# With ``Encoding.spp`` a last channel holds the sample count, a constant log2(spp)/6 (1 at 64 spp),
# so one model can serve any spp. A buffer missing from the input (a feature a scene or a reader
# left out) is its documented background value before the encoding, so the channel count never
# depends on the scene.
# Relative-variance floor (radiance² units) and the log scale's zero, see the module docstring.
VARIANCE_FLOOR = 1e-2
RELATIVE_VARIANCE_MIN = 1e-6


def _kind(buf: Buffer) -> str:
    if buf.radiance:
        return "radiance"
    return buf.name if buf.name in ("normal", "depth") else "identity"


# (key, channels, kind) of every input channel group, in order.
TABLE: tuple[tuple[str, int, str], ...] = (
    tuple((b.name, b.size, _kind(b)) for b in BUFFERS)
    + tuple((variance_name(b.name), 1, "relative_variance") for b in BUFFERS)
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
        out += [key] if kind == "relative_variance" else [f"{key}.{c}" for c in BY_NAME[key].channels]
    return out + (["spp"] if encoding.spp else [])


def relative_variance_feature(variance: np.ndarray, mean_square: np.ndarray) -> np.ndarray:
    """``1 + log10(v / (m² + 1e-2) + 1e-6) / 6``: 0 for a noise-free pixel, ~1 for relative variance 1."""
    rel = np.maximum(variance, 0.0) / (mean_square + VARIANCE_FLOOR)
    return (1.0 + np.log10(rel + RELATIVE_VARIANCE_MIN) / 6.0).astype(np.float32)


def variance_feature(buffers: dict[str, np.ndarray], name: str, shape: tuple[int, int]) -> np.ndarray:
    """(1, H, W) ``relative_variance_feature`` of buffer ``name`` from its channel means; zeros where
    the buffer or its variance is missing."""
    v, m = buffers.get(variance_name(name)), buffers.get(name)
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
        x = np.full((H, W, n), BY_NAME[key].background, np.float32) if x is None else x.astype(np.float32)
        parts.append(np.moveaxis(_group(x, kind, encoding, rotation), 2, 0))
    if encoding.spp:
        parts.append(np.full((1, H, W), math.log2(max(int(spp), 1)) / 6.0, np.float32))
    return np.ascontiguousarray(np.concatenate(parts, axis=0), dtype=np.float32)
