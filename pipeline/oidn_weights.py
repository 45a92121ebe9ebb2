"""OIDN's trained weights, read where they are: inside pyoidn's core library, or a ``.tza`` file.

OIDN 2.x links its weights into ``libOpenImageDenoise_core``: one TZA blob (``pipeline.tza``) per
network, each under a dynamic ELF symbol ``oidn::blobs::weights::<name>`` whose value is the
blob's virtual address and whose size is its length. The names say what a network reads:
``rt_hdr`` (colour), ``rt_hdr_alb`` (+ albedo), ``rt_hdr_alb_nrm`` (+ albedo + normal, what
``pyoidn.denoise(color, albedo, normal, hdr=True, quality="high")`` runs), ``_small`` variants
for the fast quality, ``rt_ldr_*`` for LDR input, ``_calb_cnrm`` for noise-free aux, ``_large``,
``rt_alb``/``rt_nrm`` (aux prefilters) and ``rtlightmap_*``.

``load(name, tza=None)`` returns a blob's bytes: from ``tza`` when given (a file from OIDN's
public weights repository, or one ``export --format oidn`` wrote; the way on macOS and Windows,
whose libraries are not ELF), else from the library. The ELF symbol table is read with
pyelftools. Every failure is a ``WeightsError`` naming the file it looked in and the fix.
"""
from __future__ import annotations

import functools
import importlib.util
import os
import re
from pathlib import Path

from .errors import WeightsError

# Mangled form of oidn::blobs::weights::<name> (Itanium ABI: a length before each name part).
_SYMBOL = re.compile(r"^_ZN4oidn5blobs7weights(\d+)(\w+)E$")
# What each input set reads; ``network_for`` picks the name.
INPUT_SETS = {"color": "rt_hdr", "albedo": "rt_hdr_alb", "albedo_normal": "rt_hdr_alb_nrm"}
FIX = ("install pyoidn==2.5.1.0 (make setup), or give OIDN's weights as a file: oidn.weights=FILE.tza "
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
    noisy aux first denoised by its aux networks, ``pipeline.oidn.prefilter_aux``)."""
    return "_calb_cnrm" in network


def library_path() -> Path:
    """pyoidn's ``libOpenImageDenoise_core`` (found without importing pyoidn)."""
    spec = importlib.util.find_spec("pyoidn")
    if spec is None or not spec.submodule_search_locations:
        raise WeightsError(f"pyoidn is not installed, so OIDN's built-in weights are not on this machine; {FIX}")
    folder = Path(next(iter(spec.submodule_search_locations))) / "oidn" / "lib"
    found = sorted(folder.glob("libOpenImageDenoise_core.so*"), key=lambda p: len(p.name), reverse=True)
    if not found:
        raise WeightsError(f"{folder}: no libOpenImageDenoise_core.so* (not a Linux pyoidn?); {FIX}")
    return found[0]


@functools.lru_cache(maxsize=4)
def blobs(library: str) -> dict[str, tuple[int, int]]:
    """Blob name → (file offset, size) in ``library``, from its dynamic symbol table."""
    try:
        from elftools.common.exceptions import ELFError
        from elftools.elf.elffile import ELFFile
    except ImportError as exc:
        raise WeightsError(f"pyelftools is not installed ({exc}); pip install pyelftools, or {FIX}") from None
    try:
        with open(library, "rb") as fh:
            elf = ELFFile(fh)
            table = elf.get_section_by_name(".dynsym")
            if table is None:
                raise WeightsError(f"{library}: no dynamic symbol table; {FIX}")
            loads = [s for s in elf.iter_segments() if s["p_type"] == "PT_LOAD"]
            out = {}
            for sym in table.iter_symbols():
                m = _SYMBOL.match(sym.name)
                if m and len(m.group(2)) == int(m.group(1)):
                    out[m.group(2)] = (_file_offset(loads, sym["st_value"], library), int(sym["st_size"]))
    except (OSError, ELFError) as exc:
        raise WeightsError(f"{library}: cannot read it as an ELF library ({exc}); {FIX}") from None
    if not out:
        raise WeightsError(f"{library}: no oidn::blobs::weights symbols (another OIDN build?); {FIX}")
    return out


def _file_offset(loads: list, address: int, library: str) -> int:
    for seg in loads:
        if seg["p_vaddr"] <= address < seg["p_vaddr"] + seg["p_filesz"]:
            return int(address - seg["p_vaddr"] + seg["p_offset"])
    raise WeightsError(f"{library}: symbol address {address:#x} is in no loaded segment; {FIX}")


ENV = "MCDENOISE_OIDN_WEIGHTS"   # a folder of <network>.tza: OIDN's weights where pyoidn is not installed


def default_folder() -> str:
    """The folder of ``<network>.tza`` files named by the environment variable ``MCDENOISE_OIDN_WEIGHTS``
    (a machine without pyoidn, such as a lent GPU machine), or "" for pyoidn's built-in weights."""
    return os.environ.get(ENV, "")


def source(name: str, weights: str = "") -> Path | None:
    """The ``.tza`` file the config key ``oidn.weights`` gives for network ``name`` (a file as is, a
    folder's ``<name>.tza``), or None for pyoidn's built-in blob."""
    if not weights:
        return None
    path = Path(weights)
    return path / f"{name}.tza" if path.is_dir() else path


def load(name: str, tza: str | Path | None = None) -> bytes:
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
        raise WeightsError(f"{library}: no weights named {name!r} (it has {', '.join(sorted(table))}); {FIX}")
    offset, size = table[name]
    with open(library, "rb") as fh:
        fh.seek(offset)
        data = fh.read(size)
    if len(data) != size:
        raise WeightsError(f"{library}: truncated: weights {name!r} need {size} bytes at {offset}; reinstall pyoidn")
    return data
