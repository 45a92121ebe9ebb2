"""Intel Open Image Denoise, the library (``pyoidn``): the one call every stage uses (baseline, first
estimate, and OIDN running weights we trained), OIDN's built-in weights (read out of its library), and
its aux prefilter as PyTorch runs it.

Filter RT in HDR mode, quality high. Albedo and normal are the renderer's noisy buffers. By default
they go to OIDN as they are (``cleanAux`` off: the colour network trained on noisy aux, one filter
run). ``clean_aux=True`` is the mode OIDN's documentation recommends for final frames with noisy aux:
albedo and normal are first denoised by OIDN's own aux networks (an RT filter given only ``albedo``
or only ``normal``), then the colour network made for noise-free aux runs (``cleanAux`` on): three
filter runs instead of one. OIDN takes world- or view-space normals in [−1, 1] (need not be
normalised) and albedo in [0, 1]: both are clamped to those ranges before each call; negative
radiance (never produced by the renderer, possible in user EXRs) is clamped to 0.

``weights``: a float16 TZA blob (``pipeline.weights``' TZA; ``export --format oidn`` writes one) that OIDN
runs instead of its built-in network, through the filter's ``weights`` data parameter
(``oidnSetSharedFilterData``, which pyoidn's cffi does not declare: called through ctypes on the
filter handle pyoidn holds). The blob must match the inputs given (3, 6 or 9 channels); OIDN
refuses float32 blobs. One filter is kept per blob, so stock calls never see custom weights.

OIDN's weights (``weights_blob``, ``weights_source``, ``network_for``; below):
OIDN's trained weights, read where they are: inside pyoidn's core library, or a ``.tza`` file.

OIDN 2.x links its weights into ``libOpenImageDenoise_core``: one TZA blob (``pipeline.weights``' TZA) per
network, each under a dynamic ELF symbol ``oidn::blobs::weights::<name>`` whose value is the
blob's virtual address and whose size is its length. The names say what a network reads:
``rt_hdr`` (colour), ``rt_hdr_alb`` (+ albedo), ``rt_hdr_alb_nrm`` (+ albedo + normal, what
``pyoidn.denoise(color, albedo, normal, hdr=True, quality="high")`` runs), ``_small`` variants
for the fast quality, ``rt_ldr_*`` for LDR input, ``_calb_cnrm`` for noise-free aux, ``_large``,
``rt_alb``/``rt_nrm`` (aux prefilters) and ``rtlightmap_*``.

``weights_blob(name, tza=None)`` returns a blob's bytes: from ``tza`` when given (a file from OIDN's
public weights repository, or one ``export --format oidn`` wrote; the way on macOS and Windows,
whose libraries are not ELF), else from the library. The ELF symbol table is read with
pyelftools. Every failure is a ``WeightsError`` naming the file it looked in and the fix.
"""
from __future__ import annotations

import ctypes
import functools
import hashlib
import importlib.util
import os
import re
import threading
from pathlib import Path

import numpy as np

from mcdenoise.pipeline.errors import OIDNUnavailable, PipelineError, WeightsError


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


def prefilter_aux(albedo: np.ndarray, normal: np.ndarray | None, quality: str = "high"
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Albedo and normal denoised by OIDN's own aux networks (an RT filter given only that image),
    read and returned in [0, 1] and [−1, 1] (NaN as 0): the noise-free aux that ``cleanAux`` expects.
    ``train.model.prefilter_aux_twin`` runs the same networks in PyTorch (on a GPU, or where pyoidn is not
    installed)."""
    albedo = np.ascontiguousarray(np.clip(np.nan_to_num(albedo), 0, 1), dtype=np.float32)
    if normal is not None:
        normal = np.ascontiguousarray(np.clip(np.nan_to_num(normal), -1, 1), dtype=np.float32)
    filt = _aux_filter()
    albedo = np.ascontiguousarray(np.clip(filt.run("albedo", albedo, quality), 0, 1), dtype=np.float32)
    if normal is not None:
        normal = np.ascontiguousarray(np.clip(filt.run("normal", normal, quality), -1, 1), dtype=np.float32)
    return albedo, normal


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


# ---- OIDN's weights ----------------------------------------------------------------------------
# Mangled form of oidn::blobs::weights::<name> (Itanium ABI: a length before each name part).
_SYMBOL = re.compile(r"^_ZN4oidn5blobs7weights(\d+)(\w+)E$")
# What each input set reads; ``network_for`` picks the name.
INPUT_SETS = {"color": "rt_hdr", "albedo": "rt_hdr_alb", "albedo_normal": "rt_hdr_alb_nrm"}
WEIGHTS_FIX = ("install pyoidn==2.5.1.0 (make setup), or give OIDN's weights as a file: oidn.weights=FILE.tza "
       "(https://github.com/RenderKit/oidn-weights)")


def network_for(albedo: bool, normal: bool, small: bool = False) -> str:
    """The HDR network OIDN runs for these inputs (normal without albedo is not a set OIDN has)."""
    if normal and not albedo:
        raise WeightsError("OIDN has no network for colour + normal without albedo")
    name = INPUT_SETS["albedo_normal" if normal else "albedo" if albedo else "color"]
    return name + ("_small" if small else "")


def network_aux(network: str) -> tuple[str, ...]:
    """The aux buffers an OIDN colour network reads (the inverse of ``network_for``): (), ("albedo",) or
    ("albedo", "normal"); ``_calb_cnrm`` (noise-free aux) reads both."""
    return ("albedo", "normal")[: (2 if "nrm" in network else 1 if "alb" in network else 0)]


def clean_aux(network: str) -> bool:
    """Whether the network expects noise-free albedo and normal (``_calb_cnrm``: OIDN's final-frame mode,
    noisy aux first denoised by its aux networks, ``train.oidn.prefilter_aux``)."""
    return "_calb_cnrm" in network


def library_path() -> Path:
    """pyoidn's ``libOpenImageDenoise_core`` (found without importing pyoidn)."""
    spec = importlib.util.find_spec("pyoidn")
    if spec is None or not spec.submodule_search_locations:
        raise WeightsError(f"pyoidn is not installed, so OIDN's built-in weights are not on this machine; {WEIGHTS_FIX}")
    folder = Path(next(iter(spec.submodule_search_locations))) / "oidn" / "lib"
    found = sorted(folder.glob("libOpenImageDenoise_core.so*"), key=lambda p: len(p.name), reverse=True)
    if not found:
        raise WeightsError(f"{folder}: no libOpenImageDenoise_core.so* (not a Linux pyoidn?); {WEIGHTS_FIX}")
    return found[0]


@functools.lru_cache(maxsize=4)
def blobs(library: str) -> dict[str, tuple[int, int]]:
    """Blob name → (file offset, size) in ``library``, from its dynamic symbol table."""
    try:
        from elftools.common.exceptions import ELFError
        from elftools.elf.elffile import ELFFile
    except ImportError as exc:
        raise WeightsError(f"pyelftools is not installed ({exc}); pip install pyelftools, or {WEIGHTS_FIX}") from None
    try:
        with open(library, "rb") as fh:
            elf = ELFFile(fh)
            table = elf.get_section_by_name(".dynsym")
            if table is None:
                raise WeightsError(f"{library}: no dynamic symbol table; {WEIGHTS_FIX}")
            loads = [s for s in elf.iter_segments() if s["p_type"] == "PT_LOAD"]
            out = {}
            for sym in table.iter_symbols():
                m = _SYMBOL.match(sym.name)
                if m and len(m.group(2)) == int(m.group(1)):
                    out[m.group(2)] = (_file_offset(loads, sym["st_value"], library), int(sym["st_size"]))
    except (OSError, ELFError) as exc:
        raise WeightsError(f"{library}: cannot read it as an ELF library ({exc}); {WEIGHTS_FIX}") from None
    if not out:
        raise WeightsError(f"{library}: no oidn::blobs::weights symbols (another OIDN build?); {WEIGHTS_FIX}")
    return out


def _file_offset(loads: list, address: int, library: str) -> int:
    for seg in loads:
        if seg["p_vaddr"] <= address < seg["p_vaddr"] + seg["p_filesz"]:
            return int(address - seg["p_vaddr"] + seg["p_offset"])
    raise WeightsError(f"{library}: symbol address {address:#x} is in no loaded segment; {WEIGHTS_FIX}")


ENV = "MCDENOISE_OIDN_WEIGHTS"   # a folder of <network>.tza: OIDN's weights where pyoidn is not installed


def default_folder() -> str:
    """The folder of ``<network>.tza`` files named by the environment variable ``MCDENOISE_OIDN_WEIGHTS``
    (a machine without pyoidn, such as a lent GPU machine), or "" for pyoidn's built-in weights."""
    return os.environ.get(ENV, "")


def weights_source(name: str, weights: str = "") -> Path | None:
    """The ``.tza`` file the config key ``oidn.weights`` gives for network ``name`` (a file as is, a
    folder's ``<name>.tza``), or None for pyoidn's built-in blob."""
    if not weights:
        return None
    path = Path(weights)
    return path / f"{name}.tza" if path.is_dir() else path


def weights_blob(name: str, tza: str | Path | None = None) -> bytes:
    """The TZA bytes of network ``name``: the file ``tza`` if given, else the blob in pyoidn's library."""
    if tza:
        path = Path(tza)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise WeightsError(f"{path}: cannot read OIDN weights ({exc.strerror or exc}); give an existing .tza "
                               "file (oidn.weights=FILE.tza) or leave it empty for pyoidn's built-in weights") from None
        return data
    library = library_path()
    table = blobs(str(library))
    if name not in table:
        raise WeightsError(f"{library}: no weights named {name!r} (it has {', '.join(sorted(table))}); {WEIGHTS_FIX}")
    offset, size = table[name]
    with open(library, "rb") as fh:
        fh.seek(offset)
        data = fh.read(size)
    if len(data) != size:
        raise WeightsError(f"{library}: truncated: weights {name!r} need {size} bytes at {offset}; reinstall pyoidn")
    return data


