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
# Our own names come again: under a view layer (``ViewLayer.albedo.R``) the schema's names miss them.
ALIASES: dict[str, tuple[str, ...]] = {
    "color": ("Noisy Image", "Combined"),
    "albedo": ("albedo", "Denoising Albedo", "Albedo"),
    "normal": ("N", "nn", "sh_normal", "normal", "normals", "Denoising Normal", "Normal"),
}


def resolve(channels, schema_channels: dict[str, tuple[str, ...]], where: str) -> dict[str, tuple[str, ...]]:
    """For each of colour, albedo and normal that ``channels`` lacks under the schema's names
    (``schema_channels``: buffer → its channels), the channels that hold it under another tool's
    layer name, with the schema's channel suffixes (R, G, B or X, Y, Z); a layer found under several
    view layers is an error that names them (``where``: the file)."""
    names = set(channels)
    found: dict[str, tuple[str, ...]] = {}
    for buffer, layers in ALIASES.items():
        if all(c in names for c in schema_channels[buffer]):
            continue
        suffixes = [c.rsplit(".", 1)[-1] for c in schema_channels[buffer]]
        for layer in layers:
            views = sorted(view for view in {n[: -len(f"{layer}.{suffixes[0]}")] for n in names
                                             if n.endswith(f"{layer}.{suffixes[0]}")}
                           if (view == "" or (view.endswith(".") and "." not in view[:-1]))
                           and all(f"{view}{layer}.{s}" in names for s in suffixes))
            if len(views) > 1:
                raise StoreError(f"{where}: layer {layer!r} is in several view layers "
                                 f"({', '.join(v[:-1] or '(none)' for v in views)}); write one view layer per file")
            if views:
                found[buffer] = tuple(f"{views[0]}{layer}.{s}" for s in suffixes)
                break
    return found
