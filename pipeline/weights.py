"""Trained models on disk: the one place their weight files are written and read.

A trained model is a folder: its weights in safetensors (``model.safetensors``, or a named file such as
``control.safetensors``), whose metadata names the kind of model by its format tag, and ``model.json``
with the same tag and what rebuilds and checks the model (its settings, the SHA-256 of weights it was
built on, its validation scores). One tag per kind of model (``FORMATS``).

- ``save``: both files, each atomically (a kill leaves the previous model or none, never half of one);
- ``read_record``: ``model.json``, refused with one line that names the folder unless it is a model of
  that kind; ``kind``: which kind of model a folder holds;
- ``load_tensors``: the weights, from safetensors only (nothing is ever unpickled), their CRC-32 checked;
- ``check_sha256``: the weights a model was built on (a frozen base, OIDN's prior, the Isik network
  of its first estimate) are still the ones it was trained with.

Underneath, two file formats:

- safetensors (``save_safetensors`` / ``read_safetensors``): tensors + string metadata, written atomically,
  with a CRC-32 of both in the metadata (``crc32``), checked on reading where the file has one (safetensors
  itself has no checksum: a flipped bit in a weight would load silently);
- OIDN's Tensor Archive (``read_tza`` / ``write_tza``, below): the file OIDN's weights come in.

The resumable state of a run (``last.safetensors``) is ``pipeline.checkpoint``'s; where each model's run
lives and which run serves a sample count, ``pipeline.config``'s; ``train.export`` makes self-contained
model folders of these.
"""
from __future__ import annotations

import hashlib
import json
import math
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .errors import CheckpointError, WeightsError
from .exr import atomic_write_bytes, atomic_write_json, read_json

# kind -> format tag (written into both files; the tags are what runs on disk already carry)
FORMATS = {
    "affinity": "mcdenoise-affinity",          # the GT cleaner and the Isik baseline (clean.model)
    "afgsa": "mcdenoise-afgsa",                # AFGSA (train.baselines.afgsa)
    "oidn_control": "mcdenoise-oidn-control",  # the diffusion denoiser: a Control Module on OIDN's network (train.model)
    "oidn_ft": "mcdenoise-oidn-ft",            # OIDN's network fine-tuned (train.baselines.oidn_ft)
}
RECORD = "model.json"
CHECKSUM = "crc32"   # the metadata key of a file's CRC-32


def _crc32(tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> str:
    """CRC-32 of the metadata (but the checksum) and of every tensor's name, dtype, shape and bytes."""
    crc = zlib.crc32(json.dumps({k: v for k, v in metadata.items() if k != CHECKSUM}, sort_keys=True).encode())
    for name in sorted(tensors):
        t = tensors[name].detach().contiguous().cpu()
        crc = zlib.crc32(f"{name}|{t.dtype}|{list(t.shape)}".encode(), crc)
        crc = zlib.crc32(t.reshape(-1).view(torch.uint8).numpy(), crc)      # the buffer itself: no copy of a pack
    return f"{crc:08x}"


def save_safetensors(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> None:
    """``metadata``'s own ``crc32`` (of a file this was read from) is replaced by the one of what is written."""
    from safetensors.torch import save_file
    tensors = {k: v.detach().contiguous().cpu() for k, v in tensors.items()}
    metadata = {k: v for k, v in metadata.items() if k != CHECKSUM}
    metadata[CHECKSUM] = _crc32(tensors, metadata)

    def write(tmp: str) -> None:
        save_file(tensors, tmp, metadata=metadata)
        _sort_metadata(tmp)
    atomic_write_bytes(path, write)


def _sort_metadata(path: str) -> None:
    """Rewrite the file's header with its metadata keys sorted, in place (same length). safetensors writes
    them in the order of a Rust HashMap, which changes from one call to the next: two saves of the same
    tensors and metadata would differ in bytes."""
    with open(path, "r+b") as f:
        n = int.from_bytes(f.read(8), "little")
        text = f.read(n)
        header = json.loads(text)
        if "__metadata__" in header:
            header["__metadata__"] = dict(sorted(header["__metadata__"].items()))
        new = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode()
        if len(new) <= n:         # always (the same keys and values); else the file stays as written
            f.seek(8)
            f.write(new + b" " * (n - len(new)))


def read_safetensors(path: Path, what: str, fix: str = "") -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """(tensors on the CPU, metadata) of a safetensors file; CheckpointError naming ``path``, saying it is
    not ``what`` and ``fix``, where it cannot be read or its CRC-32 (files this module wrote) does not match."""
    from safetensors import SafetensorError, safe_open
    try:
        with safe_open(str(path), framework="pt") as f:
            metadata = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path}: not {what} ({first})" + (f"; {fix}" if fix else "")) from None
    if CHECKSUM in metadata and metadata[CHECKSUM] != _crc32(tensors, metadata):
        raise CheckpointError(f"{path}: damaged (CRC-32 of its tensors and metadata differs from the one it was "
                              f"saved with); {fix or 'restore it or train it again'}")
    return tensors, metadata


def save(folder: Path, kind: str, tensors: dict, record: dict, weights: str = "model.safetensors") -> None:
    """Write ``folder/weights`` (``tensors``) and ``folder/model.json`` (``record``), both tagged as ``kind``."""
    fmt = FORMATS[kind]
    folder.mkdir(parents=True, exist_ok=True)
    save_safetensors(folder / weights, tensors, {"format": fmt})
    atomic_write_json(folder / RECORD, {"format": fmt, **{k: v for k, v in record.items() if k != "format"}})


def read_record(folder: Path, kinds: str | tuple[str, ...], fix: str) -> dict:
    """``folder/model.json`` of a model of one of ``kinds``; else CheckpointError naming the folder and ``fix``."""
    kinds = (kinds,) if isinstance(kinds, str) else kinds
    path = Path(folder) / RECORD
    if not path.exists():
        raise CheckpointError(f"{folder}: no trained model here ({RECORD} missing); {fix}")
    record = read_json(path, "model record")
    if record.get("format") not in [FORMATS[k] for k in kinds]:
        raise CheckpointError(f"{path}: format {record.get('format')!r}, not a {' or '.join(kinds)} model; {fix}")
    return record


def kind(folder: Path) -> str | None:
    """The kind of model in ``folder`` by its ``model.json``'s tag; None without one (or with an unknown tag)."""
    path = Path(folder) / RECORD
    if not path.exists():
        return None
    tag = read_json(path, "model record").get("format")
    return next((k for k, f in FORMATS.items() if f == tag), None)


def load_tensors(path: Path, device: str = "cpu") -> dict:
    """The tensors of a safetensors file (its CRC-32 checked where it has one); CheckpointError (one line)
    where it is not one."""
    tensors, _ = read_safetensors(path, "a usable safetensors checkpoint of this model")
    return {k: v.to(device) for k, v in tensors.items()}


def check_sha256(data: bytes | Path, expected: str, what: str, fix: str) -> None:
    """``data`` (bytes, or a file) hashes to ``expected``; else CheckpointError saying ``what`` changed and ``fix``."""
    digest = hashlib.sha256(data if isinstance(data, bytes) else Path(data).read_bytes()).hexdigest()
    if digest != expected:
        raise CheckpointError(f"{what} changed since the model was trained (SHA-256 differs); {fix}")


# ---- OIDN's Tensor Archive (TZA) -----------------------------------------------------------------
# OIDN's Tensor Archive (TZA) format: the file OIDN's weights come in, read and written here.
#
# Layout (version 2.0, little-endian), as OIDN's ``training/tza.py`` writes it and its core reads it:
#
# - header: u16 magic 0x41D7, u8 major 2, u8 minor 0, u64 offset of the table from the blob start;
# - each tensor's data, starting on a 64-byte boundary (zero padding before it);
# - the table, on a 64-byte boundary: u32 count, then per tensor u16 name length, the UTF-8 name,
#   u8 ndims, ndims × u32 shape, ndims layout characters (``oihw`` for conv weights, ``x`` for
#   biases), one dtype character (``h`` float16, ``f`` float32, ``b`` int8, ``B`` uint8), u64 offset
#   of its data from the blob start.
#
# ``write_tza(read_tza(blob)) == blob`` for every blob OIDN ships (tested): tensors keep their table order
# and the writer pads as OIDN's does. OIDN itself only runs float16 weights.
#
# The format has no checksum, so the reader holds a blob to that layout instead: each tensor starts
# at the first 64-byte boundary after the previous one (the first after the header), the table at
# the first after the last tensor, and the table ends the blob. A changed offset, shape, dtype, count
# or table position then fails with a ``TZAError`` rather than reading other bytes as weights
# (fuzzed in ``tests/test_fuzz.py``: whatever the reader accepts, it writes back byte for byte but
# for the padding).
TZA_MAGIC = 0x41D7
TZA_VERSION = (2, 0)
TZA_ALIGNMENT = 64
_TZA_DTYPES = {"h": np.float16, "f": np.float32, "b": np.int8, "B": np.uint8}
_TZA_CODES = {np.dtype(v): k for k, v in _TZA_DTYPES.items()}


class TZAError(WeightsError):
    """Bytes that are not a TZA archive this module can read (the message says what is wrong)."""


@dataclass(frozen=True)
class TZATensor:
    """One entry of an archive: the array and its layout string (``oihw``, ``x``)."""
    array: np.ndarray
    layout: str


def read_tza(blob: bytes, source: str = "TZA blob") -> dict[str, TZATensor]:
    """Name → ``Tensor`` in table order; arrays are copies (the blob may be freed). ``source`` names
    the blob in errors."""
    view = memoryview(blob)
    if len(view) < 12:
        raise TZAError(f"{source}: {len(view)} bytes, too short for a TZA header")
    magic, major, minor, table = struct.unpack_from("<HBBQ", view, 0)
    if magic != TZA_MAGIC:
        raise TZAError(f"{source}: not a TZA archive (magic {magic:#06x}, expected {TZA_MAGIC:#06x})")
    if major != TZA_VERSION[0]:
        raise TZAError(f"{source}: TZA version {major}.{minor}, this reader knows {TZA_VERSION[0]}.x")
    if not 12 <= table <= len(view) - 4:
        raise TZAError(f"{source}: table at byte {table}, outside the blob's {len(view)} bytes")
    try:
        return _read_table(view, table)
    except (struct.error, UnicodeDecodeError, KeyError, ValueError) as exc:
        if isinstance(exc, TZAError):
            raise TZAError(f"{source}: {exc}") from None
        raise TZAError(f"{source}: damaged TZA table ({type(exc).__name__}: {exc})") from None


def _aligned(pos: int) -> int:
    return pos + (-pos % TZA_ALIGNMENT)


def _read_table(view: memoryview, table: int) -> dict[str, TZATensor]:
    (count,), pos = struct.unpack_from("<I", view, table), table + 4
    out: dict[str, TZATensor] = {}
    data_end = 12            # where the previous tensor's data (at first the header) ends
    for _ in range(count):
        (n,), pos = struct.unpack_from("<H", view, pos), pos + 2
        name, pos = bytes(view[pos:pos + n]).decode(), pos + n
        (ndims,), pos = struct.unpack_from("<B", view, pos), pos + 1
        shape, pos = struct.unpack_from(f"<{ndims}I", view, pos), pos + 4 * ndims
        layout, pos = bytes(view[pos:pos + ndims]).decode("ascii"), pos + ndims
        code, pos = bytes(view[pos:pos + 1]).decode("ascii"), pos + 1
        (offset,), pos = struct.unpack_from("<Q", view, pos), pos + 8
        if len(layout) != ndims or code not in _TZA_DTYPES:
            raise TZAError(f"tensor {name!r}: layout {layout!r} / dtype {code!r} is not a TZA tensor's")
        if name in out:
            raise TZAError(f"tensor {name!r} is in the table twice")
        if offset != _aligned(data_end):
            raise TZAError(f"tensor {name!r} starts at byte {offset}, expected {_aligned(data_end)} "
                           "(data laid out as OIDN writes it)")
        dtype = np.dtype(_TZA_DTYPES[code])
        data_end = offset + math.prod(shape) * dtype.itemsize
        if data_end > table:
            raise TZAError(f"tensor {name!r} ends at byte {data_end}, past the table at {table}")
        out[name] = TZATensor(np.frombuffer(view[offset:data_end], dtype=dtype).reshape(shape).copy(), layout)
    if table != _aligned(data_end):
        raise TZAError(f"table at byte {table}, expected {_aligned(data_end)} (after the last tensor)")
    if pos != len(view):
        raise TZAError(f"table ends at byte {pos}, the blob at {len(view)}")
    return out


def write_tza(tensors: dict[str, TZATensor]) -> bytes:
    """The archive of ``tensors`` (in their order), padded as OIDN's writer pads."""
    parts, table, size = [bytearray(struct.pack("<HBBQ", TZA_MAGIC, *TZA_VERSION, 0))], [], 12
    for name, t in tensors.items():
        array = np.ascontiguousarray(t.array)
        if array.dtype not in _TZA_CODES:
            raise TZAError(f"tensor {name!r}: dtype {array.dtype} has no TZA code (float16, float32, int8, uint8)")
        if len(t.layout) != array.ndim:
            raise TZAError(f"tensor {name!r}: layout {t.layout!r} for {array.ndim} dimensions")
        pad = -size % TZA_ALIGNMENT
        parts.append(bytes(pad) + array.tobytes())
        table.append((name, array.shape, t.layout, _TZA_CODES[array.dtype], size + pad))
        size += pad + array.nbytes
    pad = -size % TZA_ALIGNMENT
    parts.append(bytes(pad))
    table_offset = size + pad
    entries = bytearray(struct.pack("<I", len(table)))
    for name, shape, layout, code, offset in table:
        raw = name.encode()
        entries += struct.pack("<H", len(raw)) + raw + struct.pack(f"<B{len(shape)}I", len(shape), *shape)
        entries += (layout + code).encode("ascii") + struct.pack("<Q", offset)
    parts.append(entries)
    parts[0][4:12] = struct.pack("<Q", table_offset)
    return b"".join(parts)
