"""Intel Open Image Denoise (``pyoidn``): the one call every stage uses (baseline, first estimate,
and OIDN running weights we trained).

Filter RT in HDR mode, quality high. Albedo and normal are the renderer's noisy buffers, so OIDN
prefilters them (``cleanAux`` off). OIDN takes world- or view-space normals in [−1, 1] (need not be
normalised) and albedo in [0, 1]: both are clamped to those ranges before the call; negative
radiance (never produced by the renderer, possible in user EXRs) is clamped to 0.

``weights``: a float16 TZA blob (``pipeline.tza``; ``export --format oidn`` writes one) that OIDN
runs instead of its built-in network, through the filter's ``weights`` data parameter
(``oidnSetSharedFilterData``, which pyoidn's cffi does not declare: called through ctypes on the
filter handle pyoidn holds). The blob must match the inputs given (3, 6 or 9 channels); OIDN
refuses float32 blobs. One filter is kept per blob, so stock calls never see custom weights.
"""
from __future__ import annotations

import ctypes
import hashlib
import threading

import numpy as np

from .errors import OIDNUnavailable, WeightsError


def available() -> str | None:
    """None when pyoidn imports, else why not."""
    try:
        import pyoidn  # noqa: F401
    except ImportError as exc:
        return f"pyoidn is not installed ({exc}); pip install pyoidn==2.5.1.0"
    return None


def _inputs(buffers: dict[str, np.ndarray], aux: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    color = np.ascontiguousarray(np.maximum(buffers["color"], 0), dtype=np.float32)
    albedo = normal = None
    if aux and "albedo" in buffers:
        albedo = np.ascontiguousarray(np.clip(buffers["albedo"], 0, 1), dtype=np.float32)
        if "normal" in buffers:
            normal = np.ascontiguousarray(np.clip(buffers["normal"], -1, 1), dtype=np.float32)
    return color, albedo, normal


def denoise(buffers: dict[str, np.ndarray], aux: bool = True, quality: str = "high",
            weights: bytes | None = None) -> np.ndarray:
    """(H, W, 3) float32 HDR from a frame's buffers (``color``; ``albedo`` and ``normal`` when
    ``aux`` and present; albedo alone is OIDN's +albedo input set). ``weights``: a TZA blob OIDN
    runs instead of its own network."""
    why = available()
    if why:
        raise OIDNUnavailable(why)
    color, albedo, normal = _inputs(buffers, aux)
    if weights is not None:
        return _custom(weights).run(color, albedo, normal, quality)
    import pyoidn
    return np.asarray(pyoidn.denoise(color, albedo, normal, hdr=True, quality=quality), dtype=np.float32)


class _CustomFilter:
    """An RT filter on its own device running a given weight blob (kept alive as long as the filter)."""

    def __init__(self, blob: bytes):
        import pyoidn
        from pyoidn.capi import oidn_ffi

        self.blob = ctypes.create_string_buffer(bytes(blob), len(blob))
        self.device = pyoidn.Device()
        self.device.commit()
        self.filter = pyoidn.Filter(self.device, pyoidn.OIDN_FILTER_TYPE_RT)
        handle = ctypes.c_void_p(int(oidn_ffi.cast("uintptr_t", self.filter._filter)))
        set_data = _capi().oidnSetSharedFilterData
        set_data(handle, b"weights", ctypes.cast(self.blob, ctypes.c_void_p), ctypes.c_size_t(len(blob)))
        self._check("setting the weights")
        self.lock = threading.Lock()

    def _check(self, what: str) -> None:
        err = self.device.get_error()
        if err:
            raise WeightsError(f"OIDN refused the custom weights while {what}: {err} (a float16 TZA blob of OIDN's "
                               "UNet for these inputs is expected; export --format oidn writes one)")

    def run(self, color, albedo, normal, quality: str) -> np.ndarray:
        import pyoidn
        levels = {"high": pyoidn.OIDN_QUALITY_HIGH, "balanced": pyoidn.OIDN_QUALITY_BALANCED,
                  "fast": pyoidn.OIDN_QUALITY_FAST, "default": pyoidn.OIDN_QUALITY_DEFAULT}
        out = np.empty_like(color)
        with self.lock:
            f = self.filter
            for name in ("albedo", "normal"):
                f.unset_image(name)
            f.set_image("color", color, pyoidn.OIDN_FORMAT_FLOAT3)
            if albedo is not None:
                f.set_image("albedo", albedo, pyoidn.OIDN_FORMAT_FLOAT3)
                if normal is not None:
                    f.set_image("normal", normal, pyoidn.OIDN_FORMAT_FLOAT3)
            f.set_image("output", out, pyoidn.OIDN_FORMAT_FLOAT3)
            f.set_bool("hdr", True)
            f.set_bool("cleanAux", False)
            f.set_quality(levels[quality])
            f.commit()
            self._check("committing the filter")
            f.execute()
            self._check("running the filter")
        return out


_FILTERS: dict[str, _CustomFilter] = {}


def _custom(blob: bytes) -> _CustomFilter:
    key = hashlib.sha256(blob).hexdigest()
    if key not in _FILTERS:
        _FILTERS[key] = _CustomFilter(blob)
    return _FILTERS[key]


def _capi():
    """OIDN's C API through ctypes (the library pyoidn loaded), with the one call pyoidn lacks declared."""
    import os

    import pyoidn
    from pyoidn.capi import wrap_dylib
    folder = os.path.join(os.path.dirname(pyoidn.__file__), "oidn", "bin" if os.name == "nt" else "lib")
    lib = ctypes.CDLL(os.path.join(folder, wrap_dylib("OpenImageDenoise")))
    lib.oidnSetSharedFilterData.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p, ctypes.c_size_t]
    lib.oidnSetSharedFilterData.restype = None
    return lib
