"""Multi-channel EXR images in the store: one image = one file, written atomically.

An image holds a set of schema buffers (``pipeline.schema``), each with its variance. Channels
that are constant over the frame are left out when ``omit_constant`` is set; the header attribute
``mcdenoise`` (JSON) records their values, and ``read_image`` restores them, so a reader never
sees a difference. Radiance and variance are float32; features are stored in the schema's dtype
(half for albedo/normal/roughness/...). Compression is lossless (ZIP, or ZSTD on request): never DWA/B44.

Two encodings of the values (``ENCODINGS``; docs/store.md, "Bytes per channel group", has the
measurements), each written with a lossless compression (``STORE_ENCODINGS``: ``render.encoding``):

- ``exact``: every value as rendered, ZIP; a format version 2 record, what every store held
  before the compact encoding existed;
- ``compact`` (the store's default, format version 4, the record's ``encoding`` says how): when
  the beauty equals the sum of the radiance components within ``BEAUTY_TOLERANCE``, its exact
  value is that sum (the reader computes it, ``schema.beauty_from_components``) and ``R, G, B``
  hold a half-precision **view** of it (``beauty_view``; record ``beauty: view``), so that every
  EXR tool shows the picture, for about 10 % more bytes a frame (docs/store.md, "What the picture
  costs"; a float32 beauty would cost 18 %); the reader never takes ``color`` from the view.
  Variances and depth stay float32 with their mantissa rounded to ``MANTISSA_BITS`` (relative
  error at most 2^-(bits+1)), so they compress well; the radiance components and the half
  features are stored exactly. ZIP by default, which every OpenEXR reader opens (2.x and 3.x);
  ``compact-zstd`` writes the same values with ZSTD, smaller but readable only with OpenEXR >= 3.5.
  Format version 3 compact images (written before the view existed) have no ``R, G, B`` at all
  (``beauty: sum``) and read as they always did.

Every image shows its picture: the beauty's ``R, G, B`` are real channels in every encoding (the
exact float32 beauty, or the compact view), never left out as a constant.

Images for people (``write_output``: a denoiser's result) store every channel, constant or not, with
ZIP; the store leaves constant channels other than the beauty's out.

Every problem with a file raises ``StoreError`` naming the path and, where it applies, the
channel and what was expected.

Reading is defensive (tests/test_fuzz.py feeds it damaged files): ``scan_exr`` checks the file's
structure in pure Python before OpenEXR sees it (magic, version, every header attribute's size,
the channel list against the schema's names and storage types, a sane data window, lossless
compression, and an offset table whose chunks all lie inside the file), so truncated files and
absurd headers are refused without allocating or decoding anything. Version 2 images carry a
``checksum`` in their record: a CRC-32 over the record (without wall-clock fields such as
``render_seconds``) and every stored channel's bytes, verified on every full read, so a bit flip
in pixel data or in a recorded constant is an error, never silently different data.
Version 1 images (written before the checksum existed) are still read, without that check.
"""
from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import re
import sys
import tempfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

from . import schema
from .errors import StoreError, StoreWriteError
from .numerics import constant_value

FORMAT = "mcdenoise-image"
FORMAT_VERSION = 4              # the compact encoding; the exact one writes version 2 records
EXACT_VERSION = 2
READ_VERSIONS = (1, 2, 3, 4)    # 1: no checksum; 3: an 'encoding' record; 4: the beauty's half view
# The beauties a compact record may state, per format version: 'sum' (version 3: no R, G, B; the
# reader sums the components), 'view' (version 4: R, G, B are a half view of that sum), 'stored'.
BEAUTIES = {3: ("sum", "stored"), 4: ("view", "stored")}
HALF_MAX = 65504.0              # the largest finite half: a view clamps brighter pixels to it
ENCODINGS = ("compact", "exact")
# Mantissa bits kept by the compact encoding (float32 has 23): variances, and the depth mean.
# Relative error <= 2^-(bits+1): 2^-6 = 1.6 % for a variance, below the sampling error of the
# variance estimate itself (sqrt(2/(n-1)): 4.4 % at 1024 spp, 82 % at 4 spp; the models' outputs
# move by < 0.002 dB, docs/store.md); 2^-11 for depth, the precision of the half features.
MANTISSA_BITS = {"variance": 5, "depth": 10}
# The beauty is derived when |beauty - sum of components| <= this x sum of |components| in every
# pixel, else stored. The renderer accumulates beauty and components separately in float32, so
# they agree only to round-off: at most 1.2e-6 (2^-19.7) over the 1548 images of data/default
# (docs/store.md), while summing 1024 float32 samples alone may err by 1024 x 2^-24 = 6e-5.
BEAUTY_TOLERANCE = 2.0 ** -18
META_KEY = "mcdenoise"
# Refuse absurd headers before allocating: 16k pixels a side, 4096² pixels in all (an image of
# every schema channel at that size decodes to ~3 GB) are far above any frame we render.
MAX_SIDE = 16384
MAX_PIXELS = 4096 * 4096
# The header is read whole for the structural check; ours are a few KiB.
MAX_HEADER_BYTES = 1 << 20
# Record fields that differ between two renders of the same image (wall-clock): not checksummed.
VOLATILE_KEYS = ("render_seconds",)
MAGIC = b"\x76\x2f\x31\x01"
# EXR compression code -> (name, scanlines per chunk); only lossless ones are accepted.
LOSSLESS = {0: ("NO", 1), 1: ("RLE", 1), 2: ("ZIPS", 1), 3: ("ZIP", 16), 4: ("PIZ", 32), 13: ("ZSTD", 1)}
# render.encoding -> (the values' encoding, the file's compression). ZIP is the default since every
# OpenEXR reader in use decodes it (2.x, 3.0-3.4: Blender, Nuke, OpenImageIO builds); ZSTD came
# with OpenEXR 3.5 (docs/compatibility.md).
STORE_ENCODINGS = {"compact": ("compact", "ZIP"), "compact-zstd": ("compact", "ZSTD"), "exact": ("exact", "ZIP")}
# The compressions an image of each encoding may have (ZSTD: compact images of stores written before
# ZIP became the default, or with compact-zstd).
COMPRESSIONS = {"compact": ("ZIP", "ZSTD"), "exact": ("ZIP",)}
PIXEL_TYPES = {1: np.dtype(np.float16), 2: np.dtype(np.float32)}   # 0 (uint) is never written


def atomic_write_bytes(path: Path, writer) -> None:
    """Call ``writer(tmp_path)`` then rename onto ``path``: readers never see a partial file.

    The temporary file lives in the same directory (rename is atomic within a file system) and
    is removed if the writer fails for any reason, including a full disk. A failure of the file
    system (full disk, read-only or not writable folder, file size limit) is a ``StoreError``
    naming the path; nothing is left behind.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise StoreWriteError(f"{path}: cannot write into {path.parent} ({_reason(exc)})") from None
    os.close(fd)
    try:
        writer(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        # mkstemp creates the file 0600; a store is shared (cluster, other users): honour the umask.
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        # OpenEXR reports I/O failures as RuntimeError with the OS message in the text.
        if isinstance(exc, OSError) or (isinstance(exc, RuntimeError) and not isinstance(exc, StoreError)
                                        and _IO_WORDS.search(str(exc))):
            raise StoreWriteError(f"{path}: writing failed, nothing was written ({_reason(exc)})") from None
        raise


_UMASK = os.umask(0o022)
os.umask(_UMASK)
_IO_WORDS = re.compile(r"No space left|Disk quota|Read-only file system|Permission denied|File too large|"
                       r"Input/output error|Failed to write|Cannot open")


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.errno is not None:
        text = os.strerror(exc.errno)
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            text += ": the disk is full"
        elif exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
            text += ": the store is not writable"
        return text
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text + (": the disk is full" if "No space left" in text else "")


def atomic_write_json(path: Path, data: Any) -> None:
    text = json.dumps(data, indent=1, sort_keys=True, allow_nan=False)

    def write(tmp: str) -> None:
        with open(tmp, "w") as f:
            f.write(text + "\n")

    atomic_write_bytes(path, write)


def read_json(path: Path, what: str = "manifest") -> dict:
    try:
        with open(path) as f:
            data = json.load(f)
    except FileNotFoundError:
        raise StoreError(f"{path}: {what} is missing") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise StoreError(f"{path}: {what} is not valid JSON ({str(exc)[:200]})") from None
    if not isinstance(data, dict):
        raise StoreError(f"{path}: {what} must be a JSON object")
    return data


def _round_to_storage(value: float, dtype: type, bits: int | None = None) -> float:
    arr = np.asarray([value], dtype=dtype)
    return float((round_mantissa(arr, bits) if bits is not None else arr)[0])


def round_mantissa(values: np.ndarray, bits: int) -> np.ndarray:
    """float32 ``values`` rounded to the nearest number with ``bits`` mantissa bits (of 23).

    |result - x| <= 2^-(bits+1) * max(|x|, 2^-126) (the float32 normal range: relative error
    2^-(bits+1)). A magnitude that would round up past the largest float32 is truncated instead,
    so finite values stay finite.
    """
    u = np.ascontiguousarray(values, dtype=np.float32).view(np.uint32)
    drop = 23 - int(bits)
    if drop <= 0:
        return u.view(np.float32).copy()
    mask = np.uint32((0xFFFFFFFF << drop) & 0xFFFFFFFF)
    out = ((u + np.uint32(1 << (drop - 1))) & mask).view(np.float32)
    overflow = ~np.isfinite(out)
    if overflow.any():
        out[overflow] = (u[overflow] & mask).view(np.float32)
    return out


def _mantissa_bits(key: str, encoding: str) -> int | None:
    """Mantissa bits the ``encoding`` keeps for array ``key`` (None: all of them)."""
    if encoding != "compact":
        return None
    if key.endswith(".variance"):
        return MANTISSA_BITS["variance"]
    return MANTISSA_BITS["depth"] if key == "depth" else None


def _schema_order(buffers: set[str]) -> list[str]:
    """Buffer names in the schema's order; names the schema lacks last (they are refused later)."""
    return sorted(buffers, key=lambda n: [b.name for b in schema.BUFFERS].index(n) if n in schema.BY_NAME else 1 << 30)


def _checked_buffer(path: Path, key: str, arrays: dict[str, np.ndarray], size: int, shape) -> np.ndarray:
    """``arrays[key]`` as an HxWx``size`` array; StoreError if missing, misshapen (``shape``: the other
    buffers' HxW, None before the first) or not finite."""
    if key not in arrays:
        raise StoreError(f"{path}: buffer {key!r} has neither data nor a constant")
    arr = np.asarray(arrays[key])
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] != size:
        raise StoreError(f"{path}: buffer {key!r} has shape {arr.shape}, expected HxWx{size}")
    if shape is not None and arr.shape[:2] != shape:
        raise StoreError(f"{path}: buffer {key!r} is {arr.shape[:2]}, other buffers are {shape}")
    if not np.all(np.isfinite(arr)):
        raise StoreError(f"{path}: buffer {key!r} has non-finite values; repair (and count) them first")
    return arr


def _buffer_channels(path: Path, buffers: list[str], arrays: dict[str, np.ndarray], constants: dict[str, float],
                     omit_constant: bool, encoding: str = "exact"
                     ) -> tuple[tuple[int, int], dict[str, np.ndarray], dict[str, float]]:
    """(HxW, stored channels, omitted channel constants) of every buffer and its variance.

    A key in ``constants`` is omitted with that value rounded to the channel's storage type; with
    ``omit_constant`` so is a channel whose stored data is constant over the frame, except the
    beauty's ``R, G, B`` (a viewer shows them). Values are rounded to the ``encoding``'s mantissa
    bits first (``_mantissa_bits``)."""
    shape = None
    channels: dict[str, np.ndarray] = {}
    omitted: dict[str, float] = {}
    for name in buffers:
        if name not in schema.BY_NAME:
            raise StoreError(f"{path}: unknown buffer {name!r} (schema has {', '.join(schema.BY_NAME)})")
        buf = schema.BY_NAME[name]
        for key, names, dtype in ((name, buf.exr_channels, buf.dtype),
                                  (schema.variance_name(name), buf.variance_channels, np.float32)):
            bits = _mantissa_bits(key, encoding)
            if key in constants:
                for ch in names:
                    omitted[ch] = _round_to_storage(constants[key], dtype, bits)
                continue
            arr = _checked_buffer(path, key, arrays, buf.size, shape)
            shape = arr.shape[:2]
            for c, ch in enumerate(names):
                data = np.ascontiguousarray(arr[..., c], dtype=dtype)
                if bits is not None:
                    data = round_mantissa(data, bits)
                value = constant_value(data) if omit_constant and key != "color" else None
                if value is not None:
                    omitted[ch] = value
                else:
                    channels[ch] = data
    if shape is None:
        raise StoreError(f"{path}: no buffer has pixel data, cannot tell the image size")
    return shape, channels, omitted


def _add_layers(path: Path, channels: dict[str, np.ndarray], layers: dict[str, np.ndarray], shape) -> None:
    """Add each extra layer (``schema.OUTPUT_LAYERS``, HxWx3) to ``channels`` as ``<name>.R/G/B``."""
    for name, arr in layers.items():
        arr = np.asarray(arr, dtype=np.float32)
        if name not in schema.OUTPUT_LAYERS or arr.shape != (*shape, 3) or not np.all(np.isfinite(arr)):
            raise StoreError(f"{path}: layer {name!r} must be one of {schema.OUTPUT_LAYERS}, a finite HxWx3 array of "
                             f"the image's size; got shape {arr.shape}")
        for c, ch in enumerate("RGB"):
            channels[f"{name}.{ch}"] = np.ascontiguousarray(arr[..., c])


def write_image(path: Path, arrays: dict[str, np.ndarray], constants: dict[str, float] | None = None,
                meta: dict | None = None, omit_constant: bool = True, layers: dict[str, np.ndarray] | None = None,
                encoding: str = "exact", compression: str | None = None, camera=None) -> dict:
    """Write buffers (``name`` and ``name.variance`` keys, HxWxC float arrays) to one EXR.

    ``constants`` maps keys that were not computed at all (pruned features) to their value.
    ``layers``: extra HxWx3 float32 layers of ``schema.OUTPUT_LAYERS`` (a denoiser's ``std``), written
    as ``<name>.R/G/B`` and listed in the record's ``layers``; readers of the buffers ignore them.
    ``encoding``: one of ``STORE_ENCODINGS`` (module docstring); 'exact' writes what this function always
    wrote (a version 2 record, ZIP). ``compression``: another lossless one than the encoding's
    (``LOSSLESS`` names; measurements). ``camera``: the frame's ``pipeline.motion.Camera``, written as the
    standard header attributes ``worldToCamera`` and ``worldToNDC`` (``CAMERA_ATTRIBUTES``; the pixels and
    the record do not change).
    Returns the image's record: buffers, omitted channel constants, shape and ``meta``.
    """
    if encoding not in STORE_ENCODINGS:
        raise StoreError(f"{path}: encoding {encoding!r} is not one of {', '.join(STORE_ENCODINGS)}")
    encoding, default_compression = STORE_ENCODINGS[encoding]
    compression = compression or default_compression
    if compression not in {name for name, _ in LOSSLESS.values()}:
        raise StoreError(f"{path}: compression {compression!r} is not a lossless EXR compression")
    constants = dict(constants or {})
    buffers = _schema_order({k.removesuffix(".variance") for k in list(arrays) + list(constants)})
    shape, channels, omitted = _buffer_channels(path, buffers, arrays, constants, omit_constant, encoding)
    _add_layers(path, channels, layers or {}, shape)
    record = {"format": FORMAT, "version": EXACT_VERSION, "buffers": buffers}
    if encoding == "compact":
        view = _beauty_view_channels(path, buffers, channels, omitted, shape)
        channels.update(view)
        for ch in view:
            omitted.pop(ch, None)
        record.update(version=FORMAT_VERSION, encoding={"name": encoding, "beauty": "view" if view else "stored",
                                                        "mantissa_bits": dict(MANTISSA_BITS),
                                                        "compression": compression})
    if not channels:
        # OpenEXR needs at least one channel: keep one constant channel (the beauty's red if it has one).
        first = schema.BY_NAME[buffers[0]].exr_channels[0]
        ch = first if first in omitted else sorted(omitted)[0]
        channels[ch] = np.full(shape, omitted.pop(ch), dtype=schema.storage_dtype(ch))
    record.update({"height": int(shape[0]), "width": int(shape[1]), "constants": dict(sorted(omitted.items())),
                   **({"layers": sorted(layers)} if layers else {}), **(meta or {})})
    record["checksum"] = checksum(record, channels)
    header = {
        "compression": getattr(OpenEXR, f"{compression}_COMPRESSION"),
        "type": OpenEXR.scanlineimage,
        META_KEY: json.dumps(record, sort_keys=True, allow_nan=False),
    }
    if camera is not None:
        from .motion import exr_matrices
        header.update(exr_matrices(camera))     # float32 4x4 arrays: OpenEXR writes them as m44f

    def write(tmp: str) -> None:
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)

    atomic_write_bytes(Path(path), write)
    return record


def write_output(path: Path, hdr: np.ndarray, meta: dict, layers: dict[str, np.ndarray] | None = None,
                 camera=None) -> dict:
    """Write an image for people (a denoiser's HDR result, with its zero variance and ``layers``): every
    channel stored whatever its values, ZIP, the exact encoding, so that any EXR tool (OpenEXR 2.x and
    later, OpenImageIO, Blender, Nuke) shows R, G, B, even of a black frame; this project reads it as any
    of its images. ``camera``: the input's, kept as ``worldToCamera``/``worldToNDC`` so that a compositor
    (or the next ``denoise --sequence``) can still reproject the result."""
    return write_image(path, {"color": hdr, "color.variance": np.zeros_like(hdr)}, meta=meta, omit_constant=False,
                       layers=layers, encoding="exact", camera=camera)


def beauty_view(color: np.ndarray) -> np.ndarray:
    """The half-precision view of an exact (float32) beauty that a compact image stores as ``R, G, B``:
    rounded to the nearest half, pixels beyond the half range clamped to +-``HALF_MAX`` (relative error
    <= 2^-11 in the half normal range, absolute <= 2^-25 below it)."""
    return np.clip(np.asarray(color, np.float32), -HALF_MAX, HALF_MAX).astype(np.float16)


def _beauty_view_channels(path: Path, buffers: list[str], channels: dict[str, np.ndarray], omitted: dict[str, float],
                          shape) -> dict[str, np.ndarray]:
    """When the reader can derive the beauty from the components (all present, the beauty within
    ``BEAUTY_TOLERANCE`` of their sum in every pixel): ``R, G, B`` as the half view of that derived
    beauty (``beauty_view``), to replace the float32 beauty; else {} (the beauty stays stored)."""
    if "color" not in buffers or not all(name in buffers for name in schema.RADIANCE_COMPONENTS):
        return {}
    parts = {name: _gather(path, schema.BY_NAME[name].exr_channels, channels, omitted, shape)
             for name in ("color", *schema.RADIANCE_COMPONENTS)}
    magnitude = sum(np.abs(parts[name].astype(np.float64)) for name in schema.RADIANCE_COMPONENTS)
    derived = schema.beauty_from_components(parts)
    error = np.abs(parts["color"].astype(np.float64) - derived)
    if not np.all(error <= BEAUTY_TOLERANCE * magnitude):
        return {}
    view = beauty_view(derived)
    return {ch: np.ascontiguousarray(view[..., c]) for c, ch in enumerate(schema.BY_NAME["color"].exr_channels)}


def checksum(record: dict, channels: dict[str, np.ndarray]) -> str:
    """CRC-32 of the record (less ``checksum`` and ``VOLATILE_KEYS``) and every stored channel."""
    skip = {"checksum", *VOLATILE_KEYS}
    text = json.dumps({k: v for k, v in record.items() if k not in skip}, sort_keys=True, allow_nan=False)
    crc = zlib.crc32(text.encode())
    for name in sorted(channels):
        arr = np.ascontiguousarray(channels[name])
        crc = zlib.crc32(f"{name}:{arr.dtype.str}:{arr.shape}".encode(), crc)
        crc = zlib.crc32(memoryview(arr).cast("B"), crc)
    return f"crc32:{crc:08x}"


def read_header(path: Path) -> dict:
    """The image's ``mcdenoise`` record, without reading pixels (so without the checksum test)."""
    return _open(path, header_only=True)[0]


# Cycles stamps every EXR it writes with its sample count per view layer (``cycles.ViewLayer.samples``, a string).
CYCLES_SAMPLES = re.compile(r"cycles\.[^.]+\.samples")
MAX_SAMPLES = 1 << 24


def renderer_samples(path: Path) -> int | None:
    """The sample count another renderer wrote in an EXR's header (Cycles: ``cycles.<view layer>.samples``), when
    its view layers agree on one whole number from 1 to ``MAX_SAMPLES``; None otherwise or for an unreadable file."""
    said: list[str] = []
    try:
        with library_output(said), OpenEXR.File(str(path), header_only=True) as f:
            # read inside: the header empties when the file closes
            found = {str(v).strip() for k, v in f.header().items() if CYCLES_SAMPLES.fullmatch(k)}
    except Exception:       # not ours to judge here: the reader of its pixels says what is wrong with the file
        return None
    if len(found) != 1 or not (value := found.pop()).isdigit() or not 0 < int(value) <= MAX_SAMPLES:
        return None
    return int(value)


def scan_exr(path: Path) -> dict:
    """Check an EXR's structure without OpenEXR: ``{width, height, channels: {name: dtype}}``.

    Refuses (``StoreError`` naming the path) anything this store never writes or cannot be
    decoded safely: other magic/version, tiled/deep/multi-part files, truncated or oversized
    header attributes, channels of unknown names, other storage types than the schema's, or
    subsampled, a data window outside 1..``MAX_SIDE`` a side or above ``MAX_PIXELS``, lossy
    compression, and chunk offsets/sizes that point outside the file.
    """
    path = Path(path)

    def fail(msg: str):
        raise StoreError(f"{path}: {msg}")

    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(min(size, MAX_HEADER_BYTES))
            if head[:4] != MAGIC:
                fail("not an OpenEXR file (bad magic number)")
            if len(head) < 8:
                fail("corrupt or truncated EXR (no version field)")
            version = int.from_bytes(head[4:8], "little")
            if version & 0xFF != 2:
                fail(f"EXR file version {version & 0xFF}, expected 2")
            if version & ~0x4FF:
                fail("tiled, deep or multi-part EXR: the store holds single-part scanline images only")
            attrs, table = _attributes(head, 255 if version & 0x400 else 31, fail)
            info = {**_header_info(attrs, fail), "table": table}
            _check_chunks(f, size, info, fail)
    except OSError as exc:
        raise StoreError(f"{path}: cannot read ({_reason(exc)})") from None
    return info


def _attributes(head: bytes, max_name: int, fail) -> tuple[dict, int]:
    """Header attributes ``{name: (type, value bytes)}`` and where the offset table starts."""
    attrs: dict[str, tuple[str, bytes]] = {}
    pos = 8

    def cstr(what: str) -> str:
        nonlocal pos
        end = head.find(b"\0", pos, pos + max_name + 1)
        if end < 0:
            fail(f"corrupt or truncated EXR header ({what} at byte {pos} is not terminated)")
        text = head[pos:end].decode("latin-1")
        pos = end + 1
        return text

    while True:
        if pos >= len(head):
            fail("corrupt or truncated EXR header (no end marker)")
        if head[pos] == 0:
            return attrs, pos + 1
        name = cstr("attribute name")
        kind = cstr(f"type of attribute {name!r}")
        if pos + 4 > len(head):
            fail(f"corrupt or truncated EXR header (size of attribute {name!r})")
        n = int.from_bytes(head[pos:pos + 4], "little", signed=True)
        pos += 4
        if n < 0 or pos + n > len(head):
            fail(f"EXR header attribute {name!r} claims {n} bytes, beyond the end of the header")
        if name in attrs:
            fail(f"EXR header attribute {name!r} appears twice")
        attrs[name] = (kind, head[pos:pos + n])
        pos += n


# The standard camera attributes (pipeline.motion: Imath row-vector matrices). Ours are m44f; m44d (a
# double matrix, as some writers make) is read too. Their size and finiteness are checked on every scan.
CAMERA_ATTRIBUTES = ("worldToCamera", "worldToNDC")
_MATRIX_TYPES = {"m44f": (64, "<f4"), "m44d": (128, "<f8")}

_REQUIRED = {"channels": ("chlist", None), "compression": ("compression", 1), "dataWindow": ("box2i", 16),
             "displayWindow": ("box2i", 16), "lineOrder": ("lineOrder", 1), "pixelAspectRatio": ("float", 4),
             "screenWindowCenter": ("v2f", 8), "screenWindowWidth": ("float", 4)}


def _header_info(attrs: dict, fail) -> dict:
    for name, (kind, n) in _REQUIRED.items():
        if name not in attrs:
            fail(f"EXR header lacks the required attribute {name!r}")
        if attrs[name][0] != kind or (n is not None and len(attrs[name][1]) != n):
            fail(f"EXR header attribute {name!r} is {attrs[name][0]!r} of {len(attrs[name][1])} bytes, "
                 f"expected {kind!r}" + (f" of {n} bytes" if n else ""))
    x0, y0, x1, y1 = (int.from_bytes(attrs["dataWindow"][1][i:i + 4], "little", signed=True) for i in range(0, 16, 4))
    w, h = x1 - x0 + 1, y1 - y0 + 1
    if not (0 < w <= MAX_SIDE and 0 < h <= MAX_SIDE and w * h <= MAX_PIXELS):
        fail(f"EXR data window {w}x{h} is not a valid size (1..{MAX_SIDE} a side, at most {MAX_PIXELS} pixels)")
    comp = attrs["compression"][1][0]
    if comp not in LOSSLESS:
        fail(f"EXR compression {comp} is lossy or unknown (the store uses lossless ZIP, or ZSTD)")
    if attrs["lineOrder"][1][0] > 2:
        fail(f"EXR line order {attrs['lineOrder'][1][0]} is not valid")
    from . import schema
    expected = {ch: (np.dtype(schema.storage_dtype(ch)),) for ch in schema.exr_channel_map()}
    expected.update({ch: (np.dtype(t),) for ch, t in schema.output_layer_channels().items()})
    # the beauty is float32, or its half view (a compact image; _check_encoding matches it to the record)
    expected.update({ch: (np.dtype(np.float32), np.dtype(np.float16)) for ch in schema.BY_NAME["color"].exr_channels})
    channels: dict[str, np.dtype] = {}
    data, pos = attrs["channels"][1], 0
    while True:
        if pos >= len(data):
            fail("EXR channel list is not terminated")
        if data[pos] == 0:
            break
        end = data.find(b"\0", pos)
        if end < 0 or end + 17 > len(data):
            fail("EXR channel list is truncated")
        name = data[pos:end].decode("latin-1")
        ptype = int.from_bytes(data[end + 1:end + 5], "little", signed=True)
        xs = int.from_bytes(data[end + 9:end + 13], "little", signed=True)
        ys = int.from_bytes(data[end + 13:end + 17], "little", signed=True)
        pos = end + 17
        if name not in expected:
            fail(f"channel {name!r} is not a channel of the schema")
        if name in channels:
            fail(f"channel {name!r} is listed twice")
        allowed = " or ".join(t.name for t in expected[name])
        if ptype not in PIXEL_TYPES:
            fail(f"channel {name!r} has EXR pixel type {ptype}, expected {allowed}")
        if PIXEL_TYPES[ptype] not in expected[name]:
            fail(f"channel {name!r} is {PIXEL_TYPES[ptype].name}, expected {allowed}")
        if (xs, ys) != (1, 1):
            fail(f"channel {name!r} is subsampled ({xs}x{ys}); the store never subsamples")
        channels[name] = PIXEL_TYPES[ptype]
    if not channels:
        fail("EXR file has no channels")
    lines = LOSSLESS[comp][1]
    return {"width": w, "height": h, "y0": y0, "channels": channels, "compression": LOSSLESS[comp][0],
            "lines": lines, "chunks": math.ceil(h / lines),
            "row_bytes": w * sum(dt.itemsize for dt in channels.values()), "matrices": _matrices(attrs, fail)}


def _matrices(attrs: dict, fail) -> dict[str, np.ndarray]:
    """The header's camera attributes (``CAMERA_ATTRIBUTES``) present, as 4x4 float64 arrays (row-vector
    convention, as stored); ``fail`` on another type, a wrong size or a value that is not finite."""
    out = {}
    for name in CAMERA_ATTRIBUTES:
        if name not in attrs:
            continue
        kind, raw = attrs[name]
        if kind not in _MATRIX_TYPES or len(raw) != _MATRIX_TYPES[kind][0]:
            fail(f"EXR header attribute {name!r} is {kind!r} of {len(raw)} bytes, expected 'm44f' of 64 bytes "
                 "(or 'm44d' of 128)")
        m = np.frombuffer(raw, dtype=_MATRIX_TYPES[kind][1]).astype(np.float64).reshape(4, 4)
        if not np.all(np.isfinite(m)):
            fail(f"EXR header attribute {name!r} has values that are not finite")
        out[name] = m
    return out


def read_camera(path: Path):
    """The ``pipeline.motion.Camera`` of any EXR whose header has the standard ``worldToCamera`` and
    ``worldToNDC`` attributes (a store image, or another renderer's with the same conventions), its image
    size the display window's. Only the header is read, in pure Python; StoreError naming the file and
    what is missing or unusable."""
    path = Path(path)

    def fail(msg: str):
        raise StoreError(f"{path}: {msg}")

    try:
        with open(path, "rb") as f:
            head = f.read(MAX_HEADER_BYTES)
    except OSError as exc:
        raise StoreError(f"{path}: cannot read ({_reason(exc)})") from None
    if head[:4] != MAGIC or len(head) < 8:
        fail("not an OpenEXR file (bad magic number)")
    version = int.from_bytes(head[4:8], "little")
    if version & 0x1000:
        fail("a multi-part EXR: read the camera of a single-part image")
    attrs, _ = _attributes(head, 255 if version & 0x400 else 31, fail)
    matrices = _matrices(attrs, fail)
    missing = [n for n in CAMERA_ATTRIBUTES if n not in matrices]
    if missing:
        fail(f"no camera: header attribute {' and '.join(map(repr, missing))} missing (images rendered before "
             "cameras were recorded have none)")
    window = attrs.get("displayWindow")
    if window is None or window[0] != "box2i" or len(window[1]) != 16:
        fail("EXR header lacks a valid 'displayWindow'")
    x0, y0, x1, y1 = (int.from_bytes(window[1][i:i + 4], "little", signed=True) for i in range(0, 16, 4))
    from .motion import camera_from_exr  # only for an EXR that has a camera: plain EXRs never load it
    return camera_from_exr(matrices["worldToCamera"], matrices["worldToNDC"], x1 - x0 + 1, y1 - y0 + 1, str(path))


def _check_chunks(f, size: int, info: dict, fail) -> None:
    """Every chunk of the offset table lies inside the file, for the right lines, not oversized."""
    n, table = info["chunks"], info["table"]
    end = table + 8 * n
    if end > size:
        fail(f"corrupt or truncated EXR: the offset table of {n} chunks ends at byte {end}, the file has {size}")
    f.seek(table)
    offsets = np.frombuffer(f.read(8 * n), dtype="<u8")
    for i, off in enumerate(offsets.tolist()):
        if not end <= off <= size - 8:
            fail(f"corrupt or truncated EXR: chunk {i} at byte {off} lies outside the file ({size} bytes)")
        f.seek(off)
        y = int.from_bytes(f.read(4), "little", signed=True)
        nbytes = int.from_bytes(f.read(4), "little", signed=True)
        rows = min(info["lines"], info["height"] - i * info["lines"])
        if y != info["y0"] + i * info["lines"]:
            fail(f"corrupt or truncated EXR: chunk {i} is for line {y}, expected {info['y0'] + i * info['lines']}")
        if not 0 < nbytes <= rows * info["row_bytes"] or off + 8 + nbytes > size:
            fail(f"corrupt or truncated EXR: chunk {i} claims {nbytes} bytes at byte {off} "
                 f"(file {size} bytes, at most {rows * info['row_bytes']} expected)")


def _open(path: Path, header_only: bool = False):
    path = Path(path)
    if not path.exists():
        raise StoreError(f"{path}: image is missing")
    info = scan_exr(path)
    try:
        f = OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
        header = f.header()
    except Exception as exc:  # OpenEXR raises ValueError/RuntimeError/IOError depending on the damage
        raise StoreError(f"{path}: corrupt or truncated EXR ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    raw = header.get(META_KEY)
    if not isinstance(raw, str):
        raise StoreError(f"{path}: header attribute {META_KEY!r} is missing: not an image written by this pipeline")
    try:
        record = json.loads(raw, parse_constant=_no_constant)
    except (json.JSONDecodeError, ValueError, RecursionError) as exc:
        raise StoreError(f"{path}: header attribute {META_KEY!r} is not valid JSON ({exc})") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise StoreError(f"{path}: header attribute {META_KEY!r} is not a {FORMAT} record")
    if record.get("version") not in READ_VERSIONS:
        raise StoreError(f"{path}: image format version {record.get('version')!r}, this code reads "
                         f"{', '.join(map(str, READ_VERSIONS))}")
    if record["version"] >= 2 and not isinstance(record.get("checksum"), str):
        raise StoreError(f"{path}: header record has no checksum (format version {record['version']} requires one)")
    h, w = record.get("height"), record.get("width")
    if not (isinstance(h, int) and isinstance(w, int) and 0 < h <= MAX_SIDE and 0 < w <= MAX_SIDE):
        raise StoreError(f"{path}: image size {w!r}x{h!r} is not a valid size (1..{MAX_SIDE})")
    if (info["height"], info["width"]) != (h, w):
        raise StoreError(f"{path}: data window {info['width']}x{info['height']} disagrees with the recorded {w}x{h}")
    _check_encoding(path, record, info["channels"])
    return record, f, header


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def read_image(path: Path, buffers: list[str] | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Read an image: ``{name: HxWxC float32, name.variance: ...}`` with constants restored and a
    derived beauty summed from its components (the compact encoding; ``R, G, B``, where they are its
    half view, are only checked against it, never returned).

    ``buffers`` restricts the result to those buffers (faster for consumers that need few).
    """
    record, f, _ = _open(path)
    stored = record.get("buffers")
    if not isinstance(stored, list) or not all(isinstance(b, str) for b in stored):
        raise StoreError(f"{path}: header lists no buffers")
    for name in stored:
        if name not in schema.BY_NAME:
            raise StoreError(f"{path}: unknown buffer {name!r} in header")
    wanted = stored if buffers is None else list(buffers)
    for name in wanted:
        if name not in stored:
            raise StoreError(f"{path}: image holds no buffer {name!r} (has {', '.join(stored)})")
    constants = record.get("constants", {})
    if not isinstance(constants, dict):
        raise StoreError(f"{path}: header 'constants' must be a mapping")
    h, w = record["height"], record["width"]
    try:
        pixels = {name: ch.pixels for name, ch in f.channels().items()}
    except Exception as exc:
        raise StoreError(f"{path}: corrupt or truncated EXR pixel data ({type(exc).__name__}: {exc})") from None
    derive = "color" in wanted and _beauty_derived(record)
    view = derive and encoding_of(record).get("beauty") == "view"
    need = list(dict.fromkeys(wanted + (list(schema.RADIANCE_COMPONENTS) if derive else [])))
    arrays: dict[str, np.ndarray] = {}
    for name in need:
        buf = schema.BY_NAME[name]
        for key, names, dtype in ((name, buf.exr_channels, buf.dtype),
                                  (schema.variance_name(name), buf.variance_channels, np.float32)):
            if not (derive and key == "color"):
                arrays[key] = _gather(path, names, pixels, constants, (h, w), dtype, name)
    if derive:
        arrays["color"] = schema.beauty_from_components(arrays)
    if view:
        _check_view(path, pixels, arrays["color"], (h, w))
    if "checksum" in record:
        if any(p is None or p.shape != (h, w) for p in pixels.values()):
            raise StoreError(f"{path}: a channel's pixel data does not have the shape {(h, w)}")
        actual = checksum(record, pixels)
        if actual != record["checksum"]:
            raise StoreError(f"{path}: checksum mismatch (header {record['checksum']!r}, data {actual!r}): "
                             f"the file is damaged")
    return {key: arrays[key] for name in wanted for key in (name, schema.variance_name(name))}, record


def _check_view(path: Path, pixels: dict, color: np.ndarray, shape) -> None:
    """The stored ``R, G, B`` of a ``beauty: view`` image are ``beauty_view`` of the derived ``color``, bit for
    bit (pixels where ``color`` is not finite are left to the caller: the writer never writes them)."""
    stored = _gather(path, schema.BY_NAME["color"].exr_channels, pixels, {}, shape, np.float16, "color")
    finite = np.isfinite(color)
    differ = int(np.count_nonzero(stored[finite] != beauty_view(color[finite]).astype(np.float32)))
    if differ:
        raise StoreError(f"{path}: channels R, G, B (the beauty's half view) differ from the beauty derived from the "
                         f"components in {differ} values: the file was changed")


def _gather(path: Path, names: tuple[str, ...], pixels: dict, constants: dict, shape, dtype: type | None = None,
            buffer: str | None = None) -> np.ndarray:
    """HxWxlen(``names``) float32 array of EXR channels ``names``, each from ``pixels`` (checked against
    ``shape`` and, given, the storage ``dtype``) or its recorded constant."""
    arr = np.empty((*shape, len(names)), dtype=np.float32)
    for c, ch in enumerate(names):
        if ch in pixels:
            pix = pixels[ch]
            if pix is None or pix.shape != tuple(shape):
                raise StoreError(f"{path}: channel {ch!r} has shape {None if pix is None else pix.shape}, "
                                 f"expected {tuple(shape)}")
            if dtype is not None and pix.dtype != dtype:
                raise StoreError(f"{path}: channel {ch!r} is {pix.dtype}, expected {np.dtype(dtype).name}")
            arr[..., c] = pix
        elif ch in constants:
            value = constants[ch]
            if not isinstance(value, (int, float)) or not np.isfinite(value):
                raise StoreError(f"{path}: constant for channel {ch!r} is {value!r}, expected a finite number")
            arr[..., c] = value
        else:
            raise StoreError(f"{path}: channel {ch!r} of buffer {buffer!r} is missing (neither stored nor a "
                             f"recorded constant)")
    return arr


def encoding_of(record: dict) -> dict:
    """An image record's encoding (its header's, or its copy in frame.json): a version 3 or 4 record says
    it; older images are all exact with the beauty stored."""
    if record.get("version") in tuple(BEAUTIES) and isinstance(record.get("encoding"), dict):
        return record["encoding"]
    return {"name": "exact", "beauty": "stored"}


def store_encoding(record: dict) -> str:
    """The ``render.encoding`` (``STORE_ENCODINGS``) that wrote an image, from its record: compact
    records name their compression; those that do not were written before ZIP was the default, with ZSTD."""
    enc = encoding_of(record)
    if enc["name"] != "compact":
        return enc["name"]
    return "compact-zstd" if enc.get("compression", "ZSTD") == "ZSTD" else "compact"


def _beauty_derived(record: dict) -> bool:
    """Whether the reader sums the beauty from its components (``sum``: left out; ``view``: R, G, B hold its
    half view), as ``_check_encoding`` checked."""
    return encoding_of(record).get("beauty") in ("sum", "view")


def _check_encoding(path: Path, record: dict, stored_channels: dict) -> None:
    """The beauty's channels are what the record says. A version 3 or 4 record names a known encoding and a
    beauty of its version (``BEAUTIES``); a derived beauty (``sum``, ``view``) lists all its components and
    records no constant for R, G, B; ``sum`` stores no R, G, B, ``view`` stores them as half; any other
    image's stored R, G, B are float32 (``stored_channels``: ``scan_exr``'s name -> dtype)."""
    color = schema.BY_NAME["color"].exr_channels
    beauty = "stored"
    if record["version"] >= 3:
        enc, allowed = record.get("encoding"), BEAUTIES[record["version"]]
        if not (isinstance(enc, dict) and enc.get("name") in ENCODINGS and enc.get("beauty") in allowed):
            raise StoreError(f"{path}: header record 'encoding' is {enc!r}, expected "
                             f"{{'name': one of {', '.join(ENCODINGS)}, 'beauty': {' or '.join(map(repr, allowed))}, "
                             f"...}} (format version {record['version']})")
        beauty = enc["beauty"]
    if beauty == "stored":
        wrong = [f"{ch} is {stored_channels[ch].name}" for ch in color
                 if ch in stored_channels and stored_channels[ch] != np.float32]
        if wrong:
            raise StoreError(f"{path}: the beauty is stored exactly, but channel {', '.join(wrong)}, expected float32")
        return
    listed = record.get("buffers") if isinstance(record.get("buffers"), list) else []
    constants = record.get("constants") if isinstance(record.get("constants"), dict) else {}
    missing = [n for n in ("color", *schema.RADIANCE_COMPONENTS) if n not in listed]
    if beauty == "sum":
        kept = [ch for ch in color if ch in stored_channels or ch in constants]
        if missing or kept:
            raise StoreError(f"{path}: the beauty is marked as the sum of its components, but "
                             + (f"buffers {', '.join(missing)} are not listed" if missing
                                else f"channels {', '.join(kept)} are stored"))
        return
    wrong = [f"{ch} is {stored_channels[ch].name if ch in stored_channels else 'missing'}" for ch in color
             if stored_channels.get(ch) != np.float16]
    constant = [ch for ch in color if ch in constants]
    if missing or wrong or constant:
        raise StoreError(f"{path}: the beauty is marked as derived from its components with R, G, B its half view, "
                         "but " + (f"buffers {', '.join(missing)} are not listed" if missing
                                   else f"channel {', '.join(wrong)}, expected float16" if wrong
                                   else f"channels {', '.join(constant)} are recorded as constants"))


@contextlib.contextmanager
def library_output(captured: list[str]):
    """Inside: what C libraries (OpenEXR) print on the process's stdout and stderr goes to ``captured`` (its
    non-empty lines) instead of the terminal, so that a damaged file is reported in one line, ours."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    with tempfile.TemporaryFile() as sink:
        try:
            for fd in saved:
                os.dup2(sink.fileno(), fd)
            yield captured
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            for fd, old in saved.items():
                os.dup2(old, fd)
                os.close(old)
            sink.seek(0)
            captured.extend(line.strip() for line in sink.read().decode(errors="replace").splitlines() if line.strip())


def read_layers(path: Path, aliased: dict | None = None, passes: dict | None = None) -> dict[str, np.ndarray]:
    """Buffers of *any* EXR that uses the schema's channel names, or another tool's for the colour,
    albedo and normal (Mitsuba's aov integrator, Blender's passes: ``ALIASES`` below).

    ``R, G, B`` (or a colour layer of another tool) are required; every other buffer (``albedo.R``…,
    ``N.X``…, ``variance.R``…) is read when all its channels are present and left out otherwise
    (consumers treat a missing feature as its background value). No ``mcdenoise`` header is needed.
    ``aliased``, when given, receives buffer → the other tool's channels it was read from. ``passes``, when
    given, receives the passes of other tools that are not buffers: ``"Vector"``, Blender's motion vectors
    (``[view layer.]Vector.X/Y/Z/W``, (H, W, 4) float32 as written; ``pipeline.motion.from_blender_vectors``),
    when the file has them.
    An image of this store whose beauty is derived (compact: ``R, G, B`` missing or a half view) or that records
    constant buffers is read with ``read_image``, so its colour is the exact beauty, never the view, and a
    constant buffer is there.
    """
    path = Path(path)
    if path.is_dir():
        raise StoreError(f"{path}: a folder, expected an EXR file")
    if not path.is_file():
        raise StoreError(f"{path}: no such file, expected an EXR file")
    with open(path, "rb") as fh:
        if fh.read(4) != b"\x76\x2f\x31\x01":
            raise StoreError(f"{path}: not an OpenEXR file (bad magic number)")
    said: list[str] = []
    try:
        with library_output(said), OpenEXR.File(str(path), separate_channels=True) as f:
            channels = {name: ch.pixels for name, ch in f.channels().items()}
            ours = f.header().get(META_KEY)
    except Exception as exc:
        # the library's own account of the damage (it prints it) says more than the exception it raises after
        said = [line for line in said if "EXR_ERR" in line] or said
        why = said[-1].removeprefix(f"{path}: ") if said else (str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        raise StoreError(f"{path}: corrupt or truncated EXR ({why})") from None
    if _read_whole(ours):
        return read_image(path)[0]
    other = resolve(channels, {b: schema.BY_NAME[b].exr_channels for b in ALIASES}, str(path))
    if not all(c in channels for c in ("R", "G", "B")) and "color" not in other:
        raise StoreError(f"{path}: channels R, G, B (the noisy colour) are required, or a layer "
                         f"{' or '.join(repr(x) for x in ALIASES['color'])} with .R, .G, .B; "
                         f"found {', '.join(sorted(channels))}")
    out: dict[str, np.ndarray] = {}
    shape = channels[other.get("color", ("R",))[0]].shape
    for buf in schema.BUFFERS:
        for key, names in ((buf.name, other.get(buf.name, buf.exr_channels)),
                           (schema.variance_name(buf.name), buf.variance_channels)):
            if all(n in channels for n in names):
                arrs = [channels[n] for n in names]
                for n, a in zip(names, arrs):
                    if a.shape != shape:
                        raise StoreError(f"{path}: channel {n!r} has shape {a.shape}, expected {shape}")
                out[key] = np.stack(arrs, axis=2).astype(np.float32)
    if not all(n in out for n in schema.RADIANCE_COMPONENTS) and (
            split := cycles_components(channels, out["color"], str(path))) is not None:
        out.update(split[0])            # Cycles' light passes
        other.update(split[1])
    if aliased is not None:
        aliased.update(other)
    if passes is not None and (vector := _vector_pass(channels, shape, path)) is not None:
        passes["Vector"] = vector
    return out


def _vector_pass(channels: dict[str, np.ndarray], shape, path: Path) -> np.ndarray | None:
    """Blender's ``Vector`` pass (H, W, 4) float32 of a file's ``channels``, None when it has none."""
    if (vector := find_layer(set(channels), "Vector", "XYZW", str(path))) is None:
        return None
    if any(channels[n].shape != shape for n in vector):
        raise StoreError(f"{path}: the Vector pass's channels are not {shape[1]}x{shape[0]}, the colour's size")
    return np.stack([channels[n] for n in vector], axis=2).astype(np.float32)


def _read_whole(raw) -> bool:
    """Whether a header's ``mcdenoise`` attribute (``raw``) is a record of this store that only ``read_image`` reads
    whole: a derived beauty, or buffers recorded as constants (a feature the scene lacks, such as an emission of
    0 everywhere), which have no channels."""
    try:
        record = json.loads(raw) if isinstance(raw, str) else None
    except (json.JSONDecodeError, ValueError, RecursionError):
        return False
    return (isinstance(record, dict) and record.get("format") == FORMAT
            and (_beauty_derived(record) or bool(record.get("constants"))))


# ---- Other tools' layer names (Mitsuba's aov integrator, Blender), for denoise --exr -------------
# Where other tools put the colour, albedo and normal in an EXR, for ``denoise --exr``.
#
# Our schema names them ``R,G,B``, ``albedo.R/G/B`` and ``N.X/Y/Z``. Other tools write:
#
# - Mitsuba 3's ``aov`` integrator: ``R,G,B`` and each AOV under the name the scene gave it, e.g.
#   ``aovs="albedo:albedo,nn:sh_normal"`` → ``albedo.R/G/B``, ``nn.X/Y/Z``;
# - Blender (Cycles) multilayer EXRs: ``<view layer>.Combined.R/G/B/A``, with the Denoising Data
#   pass ``<view layer>.Noisy Image.R/G/B`` (the colour before Blender's own denoiser),
#   ``<view layer>.Denoising Albedo.R/G/B`` and ``<view layer>.Denoising Normal.X/Y/Z``, and the Z pass
#   ``<view layer>.Depth.Z`` (motion vectors' depth test, ``pipeline.motion.flow``).
#
# ``resolve`` maps the channel names of a file onto the schema's buffers: the schema's own names
# first, then the layer names below in order, under no prefix or exactly one (a view layer).
# OIDN, and so every method here, takes normals in any consistent space (world or camera).
# buffer -> layer names, most specific first ("Noisy Image" is Combined before Blender denoised it).
# Our own names come again: under a view layer (``ViewLayer.albedo.R``) the schema's names miss them.
ALIASES: dict[str, tuple[str, ...]] = {
    "color": ("Noisy Image", "Combined"),
    "albedo": ("albedo", "Denoising Albedo", "Albedo"),
    "normal": ("N", "nn", "sh_normal", "normal", "normals", "Denoising Normal", "Normal"),
    "depth": ("depth", "Depth", "Denoising Depth"),       # Blender's Z pass: Depth.Z
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
            if (hit := find_layer(names, layer, suffixes, where)) is not None:
                found[buffer] = hit
                break
    return found


# Cycles' light passes (View Layer Properties → Passes → Light), under both spellings Blender has written them.
# Each light pass is the light divided by its lobe's colour pass, so the lobe's share of the beauty is their
# product (Blender's manual: Combined = (DiffDir + DiffInd) × DiffCol + (GlossDir + GlossInd) × GlossCol +
# (TransDir + TransInd) × TransCol + Emit + Env + the volume passes).
CYCLES_LOBES: dict[str, tuple[tuple[str, str], tuple[str, str], tuple[str, str]]] = {
    # lobe: (direct, indirect, colour)
    "diffuse": (("DiffDir", "Diffuse Direct"), ("DiffInd", "Diffuse Indirect"), ("DiffCol", "Diffuse Color")),
    "glossy": (("GlossDir", "Glossy Direct"), ("GlossInd", "Glossy Indirect"), ("GlossCol", "Glossy Color")),
    "transmission": (("TransDir", "Transmission Direct"), ("TransInd", "Transmission Indirect"),
                     ("TransCol", "Transmission Color")),
}
# Below this share of the beauty (summed over the image) the light passes may exceed it, from rounding (half-float
# passes: 2^-11 relative each); above it they are not the beauty's parts (a denoised Combined, another render).
CYCLES_EXCESS = 1e-2


def cycles_components(channels: dict[str, np.ndarray], color: np.ndarray, where: str
                      ) -> tuple[dict[str, np.ndarray], dict[str, tuple[str, ...]]] | None:
    """The radiance components (``schema.RADIANCE_COMPONENTS``) of a Cycles render from its light passes, and the
    channels each was made of; None without the diffuse and glossy passes (direct, indirect, colour), or where
    the passes add up to more than the beauty ``color`` by over ``CYCLES_EXCESS`` of it.

    The diffuse lobe's direct and indirect light times its colour are ``diffuse_direct`` and ``diffuse_indirect``;
    the glossy lobe's, with the transmission lobe's where its passes are there, ``specular_direct`` and
    ``specular_indirect``; ``emission`` is the beauty less those four, so it holds the emitters, the world and
    whatever the file has no pass for (volumes, an older Cycles' subsurface), and the five add up to the beauty
    exactly, as this store's do. What ``emission`` holds stays each frame's own in a sequence, as the
    reflections do; the diffuse light is what the temporal methods average."""
    names = set(channels)
    found = {}
    for lobe, roles in CYCLES_LOBES.items():
        layers = [next((hit for layer in spellings if (hit := find_layer(names, layer, "RGB", where))), None)
                  for spellings in roles]
        if all(layers):
            found[lobe] = layers
        elif lobe != "transmission":
            return None
    parts, used = {}, {}
    for part, role, lobes in (("diffuse_direct", 0, ("diffuse",)), ("diffuse_indirect", 1, ("diffuse",)),
                              ("specular_direct", 0, ("glossy", "transmission")),
                              ("specular_indirect", 1, ("glossy", "transmission"))):
        total = np.zeros(color.shape, np.float64)
        for lobe in (lb for lb in lobes if lb in found):
            light, colour = found[lobe][role], found[lobe][2]
            if any(channels[c].shape != color.shape[:2] for c in (*light, *colour)):
                raise StoreError(f"{where}: the {lobe} light passes are not {color.shape[1]}x{color.shape[0]}, "
                                 "the colour's size")
            total += (np.stack([channels[c] for c in light], -1).astype(np.float64)
                      * np.stack([channels[c] for c in colour], -1))
            used[part] = (*used.get(part, ()), *light, *colour)
        parts[part] = total
    emission = color.astype(np.float64) - sum(parts.values())
    if np.maximum(-emission, 0).sum() > CYCLES_EXCESS * np.abs(color).sum():
        return None
    parts["emission"] = emission
    return {k: v.astype(np.float32) for k, v in parts.items()}, used


def find_layer(names: set[str], layer: str, suffixes, where: str) -> tuple[str, ...] | None:
    """The channels ``layer.<suffix>`` for every suffix, under no prefix or exactly one view layer
    (``ViewLayer.Vector.X``); None when absent, StoreError naming ``where`` when several view layers have it."""
    views = sorted(view for view in {n[: -len(f"{layer}.{suffixes[0]}")] for n in names
                                     if n.endswith(f"{layer}.{suffixes[0]}")}
                   if (view == "" or (view.endswith(".") and "." not in view[:-1]))
                   and all(f"{view}{layer}.{s}" in names for s in suffixes))
    if len(views) > 1:
        raise StoreError(f"{where}: layer {layer!r} is in several view layers "
                         f"({', '.join(v[:-1] or '(none)' for v in views)}); write one view layer per file")
    return tuple(f"{views[0]}{layer}.{s}" for s in suffixes) if views else None
