"""Where other tools put the colour, albedo and normal in an EXR, for ``denoise --exr``.

Our schema names them ``R,G,B``, ``albedo.R/G/B`` and ``N.X/Y/Z``. Other tools write:

- Mitsuba 3's ``aov`` integrator: ``R,G,B`` and each AOV under the name the scene gave it, e.g.
  ``aovs="albedo:albedo,nn:sh_normal"`` → ``albedo.R/G/B``, ``nn.X/Y/Z``;
- Blender (Cycles) multilayer EXRs: ``<view layer>.Combined.R/G/B/A``, with the Denoising Data
  pass ``<view layer>.Noisy Image.R/G/B`` (the colour before Blender's own denoiser),
  ``<view layer>.Denoising Albedo.R/G/B`` and ``<view layer>.Denoising Normal.X/Y/Z``.

``resolve`` maps the channel names of a file onto the schema's buffers: the schema's own names
first, then the layer names below in order, under no prefix or exactly one (a view layer).
OIDN, and so every method here, takes normals in any consistent space (world or camera).
"""
from __future__ import annotations

from .errors import StoreError

# buffer -> layer names, most specific first ("Noisy Image" is Combined before Blender denoised it).
ALIASES: dict[str, tuple[str, ...]] = {
    "color": ("Noisy Image", "Combined"),
    "albedo": ("albedo", "Denoising Albedo", "Albedo"),
    "normal": ("N", "nn", "sh_normal", "normal", "normals", "Denoising Normal", "Normal"),
}
SUFFIXES = {"color": ("R", "G", "B"), "albedo": ("R", "G", "B"), "normal": ("X", "Y", "Z")}


def resolve(channels, schema_channels: dict[str, tuple[str, ...]], where: str) -> dict[str, tuple[str, ...]]:
    """For each of colour, albedo and normal that ``channels`` lacks under the schema's names
    (``schema_channels``: buffer → its channels), the channels that hold it under another tool's
    layer name; a layer found under several view layers is an error that names them (``where``: the file)."""
    names = set(channels)
    found: dict[str, tuple[str, ...]] = {}
    for buffer, layers in ALIASES.items():
        if all(c in names for c in schema_channels[buffer]):
            continue
        for layer in layers:
            prefixes = sorted({n[: -len(f"{layer}.{s}")] for n in names for s in SUFFIXES[buffer][:1]
                               if n.endswith(f"{layer}.{s}")})
            prefixes = [p for p in prefixes if (p == "" or (p.endswith(".") and "." not in p[:-1]))
                        and all(f"{p}{layer}.{s}" in names for s in SUFFIXES[buffer])]
            if len(prefixes) > 1:
                raise StoreError(f"{where}: layer {layer!r} is in several view layers "
                                 f"({', '.join(p[:-1] or '(none)' for p in prefixes)}); write one view layer per file")
            if prefixes:
                found[buffer] = tuple(f"{prefixes[0]}{layer}.{s}" for s in SUFFIXES[buffer])
                break
    return found
