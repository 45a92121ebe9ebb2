"""OIDN's Tensor Archive (TZA) format: the file OIDN's weights come in, read and written here.

Layout (version 2.0, little-endian), as OIDN's ``training/tza.py`` writes it and its core reads it:

- header: u16 magic 0x41D7, u8 major 2, u8 minor 0, u64 offset of the table from the blob start;
- each tensor's data, starting on a 64-byte boundary (zero padding before it);
- the table, on a 64-byte boundary: u32 count, then per tensor u16 name length, the UTF-8 name,
  u8 ndims, ndims × u32 shape, ndims layout characters (``oihw`` for conv weights, ``x`` for
  biases), one dtype character (``h`` float16, ``f`` float32, ``b`` int8, ``B`` uint8), u64 offset
  of its data from the blob start.

``write(read(blob)) == blob`` for every blob OIDN ships (tested): tensors keep their table order
and the writer pads as OIDN's does. OIDN itself only runs float16 weights.

The format has no checksum, so the reader holds a blob to that layout instead: each tensor starts
at the first 64-byte boundary after the previous one (the first after the header), the table at
the first after the last tensor, and the table ends the blob. A changed offset, shape, dtype, count
or table position then fails with a ``TZAError`` rather than reading other bytes as weights
(fuzzed in ``tests/test_fuzz.py``: whatever the reader accepts, it writes back byte for byte but
for the padding).
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from .errors import WeightsError

MAGIC = 0x41D7
VERSION = (2, 0)
ALIGNMENT = 64
_DTYPES = {"h": np.float16, "f": np.float32, "b": np.int8, "B": np.uint8}
_CODES = {np.dtype(v): k for k, v in _DTYPES.items()}


class TZAError(WeightsError):
    """Bytes that are not a TZA archive this module can read (the message says what is wrong)."""


@dataclass(frozen=True)
class Tensor:
    """One entry of an archive: the array and its layout string (``oihw``, ``x``)."""
    array: np.ndarray
    layout: str


def read(blob: bytes, source: str = "TZA blob") -> dict[str, Tensor]:
    """Name → ``Tensor`` in table order; arrays are copies (the blob may be freed). ``source`` names
    the blob in errors."""
    view = memoryview(blob)
    if len(view) < 12:
        raise TZAError(f"{source}: {len(view)} bytes, too short for a TZA header")
    magic, major, minor, table = struct.unpack_from("<HBBQ", view, 0)
    if magic != MAGIC:
        raise TZAError(f"{source}: not a TZA archive (magic {magic:#06x}, expected {MAGIC:#06x})")
    if major != VERSION[0]:
        raise TZAError(f"{source}: TZA version {major}.{minor}, this reader knows {VERSION[0]}.x")
    if not 12 <= table <= len(view) - 4:
        raise TZAError(f"{source}: table at byte {table}, outside the blob's {len(view)} bytes")
    try:
        return _read_table(view, table)
    except (struct.error, UnicodeDecodeError, KeyError, ValueError) as exc:
        if isinstance(exc, TZAError):
            raise TZAError(f"{source}: {exc}") from None
        raise TZAError(f"{source}: damaged TZA table ({type(exc).__name__}: {exc})") from None


def _aligned(pos: int) -> int:
    return pos + (-pos % ALIGNMENT)


def _read_table(view: memoryview, table: int) -> dict[str, Tensor]:
    (count,), pos = struct.unpack_from("<I", view, table), table + 4
    out: dict[str, Tensor] = {}
    data_end = 12            # where the previous tensor's data (at first the header) ends
    for _ in range(count):
        (n,), pos = struct.unpack_from("<H", view, pos), pos + 2
        name, pos = bytes(view[pos:pos + n]).decode(), pos + n
        (ndims,), pos = struct.unpack_from("<B", view, pos), pos + 1
        shape, pos = struct.unpack_from(f"<{ndims}I", view, pos), pos + 4 * ndims
        layout, pos = bytes(view[pos:pos + ndims]).decode("ascii"), pos + ndims
        code, pos = bytes(view[pos:pos + 1]).decode("ascii"), pos + 1
        (offset,), pos = struct.unpack_from("<Q", view, pos), pos + 8
        if len(layout) != ndims or code not in _DTYPES:
            raise TZAError(f"tensor {name!r}: layout {layout!r} / dtype {code!r} is not a TZA tensor's")
        if name in out:
            raise TZAError(f"tensor {name!r} is in the table twice")
        if offset != _aligned(data_end):
            raise TZAError(f"tensor {name!r} starts at byte {offset}, expected {_aligned(data_end)} "
                           "(data laid out as OIDN writes it)")
        dtype = np.dtype(_DTYPES[code])
        data_end = offset + math.prod(shape) * dtype.itemsize
        if data_end > table:
            raise TZAError(f"tensor {name!r} ends at byte {data_end}, past the table at {table}")
        out[name] = Tensor(np.frombuffer(view[offset:data_end], dtype=dtype).reshape(shape).copy(), layout)
    if table != _aligned(data_end):
        raise TZAError(f"table at byte {table}, expected {_aligned(data_end)} (after the last tensor)")
    if pos != len(view):
        raise TZAError(f"table ends at byte {pos}, the blob at {len(view)}")
    return out


def write(tensors: dict[str, Tensor]) -> bytes:
    """The archive of ``tensors`` (in their order), padded as OIDN's writer pads."""
    parts, table, size = [bytearray(struct.pack("<HBBQ", MAGIC, *VERSION, 0))], [], 12
    for name, t in tensors.items():
        array = np.ascontiguousarray(t.array)
        if array.dtype not in _CODES:
            raise TZAError(f"tensor {name!r}: dtype {array.dtype} has no TZA code (float16, float32, int8, uint8)")
        if len(t.layout) != array.ndim:
            raise TZAError(f"tensor {name!r}: layout {t.layout!r} for {array.ndim} dimensions")
        pad = -size % ALIGNMENT
        parts.append(bytes(pad) + array.tobytes())
        table.append((name, array.shape, t.layout, _CODES[array.dtype], size + pad))
        size += pad + array.nbytes
    pad = -size % ALIGNMENT
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
