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

from dataclasses import dataclass

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
