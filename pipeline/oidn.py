"""Intel Open Image Denoise (``pyoidn``): the one call every stage uses (baseline, first estimate,
and OIDN running weights we trained).

Filter RT in HDR mode, quality high. Albedo and normal are the renderer's noisy buffers. By default
they go to OIDN as they are (``cleanAux`` off: the colour network trained on noisy aux, one filter
run). ``clean_aux=True`` is the mode OIDN's documentation recommends for final frames with noisy aux:
albedo and normal are first denoised by OIDN's own aux networks (an RT filter given only ``albedo``
or only ``normal``), then the colour network made for noise-free aux runs (``cleanAux`` on): three
filter runs instead of one. OIDN takes world- or view-space normals in [−1, 1] (need not be
normalised) and albedo in [0, 1]: both are clamped to those ranges before each call; negative
radiance (never produced by the renderer, possible in user EXRs) is clamped to 0.

``weights``: a float16 TZA blob (``pipeline.tza``; ``export --format oidn`` writes one) that OIDN
runs instead of its built-in network, through the filter's ``weights`` data parameter
(``oidnSetSharedFilterData``, which pyoidn's cffi does not declare: called through ctypes on the
filter handle pyoidn holds). The blob must match the inputs given (3, 6 or 9 channels); OIDN
refuses float32 blobs. One filter is kept per blob, so stock calls never see custom weights.
"""
from __future__ import annotations

import ctypes
import functools
import hashlib
import threading

import numpy as np

from .errors import OIDNUnavailable, PipelineError, WeightsError


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
            weights: bytes | None = None, clean_aux: bool = False) -> np.ndarray:
    """(H, W, 3) float32 HDR from a frame's buffers (``color``; ``albedo`` and ``normal`` when
    ``aux`` and present; albedo alone is OIDN's +albedo input set). ``weights``: a TZA blob OIDN
    runs instead of its own network. ``clean_aux``: with albedo and normal, prefilter them with OIDN's
    aux networks and run the colour network for noise-free aux (a blob given in ``weights`` must then
    be one such network); OIDN has no such network for albedo alone, so without a normal the flag does
    nothing."""
    why = available()
    if why:
        raise OIDNUnavailable(why)
    color, albedo, normal = _inputs(buffers, aux)
    clean_aux = clean_aux and albedo is not None and normal is not None
    if clean_aux:
        albedo, normal = prefilter_aux(albedo, normal, quality)
    if weights is not None:
        return _custom(weights).run(color, albedo, normal, quality, clean_aux)
    import pyoidn
    return np.asarray(pyoidn.denoise(color, albedo, normal, hdr=True, clean_aux=clean_aux, quality=quality),
                      dtype=np.float32)


def prefilter_aux(albedo: np.ndarray, normal: np.ndarray | None, quality: str = "high", device: str | None = None
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Albedo and normal denoised by OIDN's own aux networks (an RT filter given only that image),
    read and returned in [0, 1] and [−1, 1] (NaN as 0): the noise-free aux that ``cleanAux`` expects.
    ``device``: a torch device to run OIDN's aux networks on in PyTorch (``pipeline.oidn_net.prefilter``,
    quality high only); also the way when pyoidn is not installed (then on the CPU)."""
    albedo = np.ascontiguousarray(np.clip(np.nan_to_num(albedo), 0, 1), dtype=np.float32)
    if normal is not None:
        normal = np.ascontiguousarray(np.clip(np.nan_to_num(normal), -1, 1), dtype=np.float32)
    if device is not None or available() is not None:
        if quality != "high":
            raise PipelineError(f"the PyTorch aux prefilter runs quality high only, not {quality!r}")
        device = device or _torch_device()
        return _twin_prefilter(albedo, device), None if normal is None else _twin_prefilter(normal, device, "normal")
    filt = _aux_filter()
    albedo = np.ascontiguousarray(np.clip(filt.run("albedo", albedo, quality), 0, 1), dtype=np.float32)
    if normal is not None:
        normal = np.ascontiguousarray(np.clip(filt.run("normal", normal, quality), -1, 1), dtype=np.float32)
    return albedo, normal


def _torch_device() -> str:
    import torch
    return "cuda" if torch.cuda.is_available() else "cpu"


def _twin_prefilter(image: np.ndarray, device: str, kind: str = "albedo") -> np.ndarray:
    import torch

    from . import oidn_net
    net = _aux_net(kind, str(device))
    x = torch.from_numpy(image).permute(2, 0, 1)[None].to(device)
    return oidn_net.prefilter(net, x, kind)[0].permute(1, 2, 0).cpu().numpy()


@functools.cache
def _aux_net(kind: str, device: str):
    from . import oidn_net, oidn_weights
    name = oidn_net.AUX_NETWORKS[kind]
    return oidn_net.load_unet(name, oidn_weights.source(name, oidn_weights.default_folder())).to(device).eval()


_QUALITY = {"high": "OIDN_QUALITY_HIGH", "balanced": "OIDN_QUALITY_BALANCED", "fast": "OIDN_QUALITY_FAST",
            "default": "OIDN_QUALITY_DEFAULT"}


class _AuxFilter:
    """One RT filter per aux image on its own device, reused across calls (OIDN builds a filter
    once and runs it many times)."""

    def __init__(self):
        import pyoidn
        self.device = pyoidn.Device()
        self.device.commit()
        self.filters: dict = {}
        self.lock = threading.Lock()

    def run(self, name: str, image: np.ndarray, quality: str) -> np.ndarray:
        import pyoidn
        out = np.empty_like(image)
        with self.lock:
            if name not in self.filters:
                self.filters[name] = pyoidn.Filter(self.device, pyoidn.OIDN_FILTER_TYPE_RT)
            f = self.filters[name]
            f.set_image(name, image, pyoidn.OIDN_FORMAT_FLOAT3)
            f.set_image("output", out, pyoidn.OIDN_FORMAT_FLOAT3)
            f.set_quality(getattr(pyoidn, _QUALITY[quality]))
            f.commit()
            _check(self.device, f"committing the {name} prefilter")
            f.execute()
            _check(self.device, f"running the {name} prefilter")
        return out


@functools.cache
def _aux_filter() -> _AuxFilter:
    return _AuxFilter()


def _check(device, what: str) -> None:
    err = device.get_error()
    if err:
        raise PipelineError(f"OIDN failed while {what}: {err}")


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

    def run(self, color, albedo, normal, quality: str, clean_aux: bool = False) -> np.ndarray:
        import pyoidn
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
            f.set_bool("cleanAux", clean_aux)
            f.set_quality(getattr(pyoidn, _QUALITY[quality]))
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
