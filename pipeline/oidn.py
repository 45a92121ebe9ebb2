"""Intel Open Image Denoise (``pyoidn``): the one call every stage uses (baseline and first estimate).

Filter RT in HDR mode, quality high. Albedo and normal are the renderer's noisy buffers, so OIDN
prefilters them (``cleanAux`` off). OIDN takes world- or view-space normals in [−1, 1] (need not be
normalised) and albedo in [0, 1]: both are clamped to those ranges before the call; negative
radiance (never produced by the renderer, possible in user EXRs) is clamped to 0.
"""
from __future__ import annotations

import numpy as np

from .errors import OIDNUnavailable


def available() -> str | None:
    """None when pyoidn imports, else why not."""
    try:
        import pyoidn  # noqa: F401
    except ImportError as exc:
        return f"pyoidn is not installed ({exc}); pip install pyoidn==2.5.1.0"
    return None


def denoise(buffers: dict[str, np.ndarray], aux: bool = True, quality: str = "high") -> np.ndarray:
    """(H, W, 3) float32 HDR from a frame's buffers (``color``; ``albedo``/``normal`` when ``aux``
    and present)."""
    why = available()
    if why:
        raise OIDNUnavailable(why)
    import pyoidn

    color = np.ascontiguousarray(np.maximum(buffers["color"], 0), dtype=np.float32)
    albedo = normal = None
    if aux and "albedo" in buffers and "normal" in buffers:
        albedo = np.ascontiguousarray(np.clip(buffers["albedo"], 0, 1), dtype=np.float32)
        normal = np.ascontiguousarray(np.clip(buffers["normal"], -1, 1), dtype=np.float32)
    return np.asarray(pyoidn.denoise(color, albedo, normal, hdr=True, quality=quality), dtype=np.float32)
