"""Multi-channel EXR images in the store: one image = one file, written atomically.

An image holds a set of schema buffers (``pipeline.schema``), each with its variance. Channels
that are constant over the frame are left out when ``omit_constant`` is set; the header attribute
``mcdenoise`` (JSON) records their values, and ``read_image`` restores them, so a reader never
sees a difference. Radiance and variance are float32; features are stored in the schema's dtype
(half for albedo/normal/roughness/...). Compression is ZIP (lossless): never DWA/B44 (lossy).

Every problem with a file raises ``StoreError`` naming the path and, where it applies, the
channel and what was expected.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

from . import schema
from .numerics import constant_value

FORMAT = "mcdenoise-image"
FORMAT_VERSION = 1
META_KEY = "mcdenoise"
# Refuse absurd headers before allocating: 16k x 16k is far above any frame we render.
MAX_SIDE = 16384


class StoreError(RuntimeError):
    """Something in the store is missing, corrupt or not what the schema expects."""


def atomic_write_bytes(path: Path, writer) -> None:
    """Call ``writer(tmp_path)`` then rename onto ``path``: readers never see a partial file.

    The temporary file lives in the same directory (rename is atomic within a file system) and
    is removed if the writer fails for any reason, including a full disk.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        writer(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


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
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StoreError(f"{path}: {what} is not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise StoreError(f"{path}: {what} must be a JSON object")
    return data


def _round_to_storage(value: float, dtype: type) -> float:
    return float(np.asarray(value, dtype=dtype))


def write_image(path: Path, arrays: dict[str, np.ndarray], constants: dict[str, float] | None = None,
                meta: dict | None = None, omit_constant: bool = True) -> dict:
    """Write buffers (``name`` and ``name.variance`` keys, HxWxC float arrays) to one EXR.

    ``constants`` maps keys that were not computed at all (pruned features) to their value.
    Returns the image's record: buffers, omitted channel constants, shape and ``meta``.
    """
    constants = dict(constants or {})
    buffers = sorted({k.removesuffix(".variance") for k in list(arrays) + list(constants)},
                     key=lambda n: [b.name for b in schema.BUFFERS].index(n) if n in schema.BY_NAME else 1 << 30)
    shape = None
    channels: dict[str, np.ndarray] = {}
    omitted: dict[str, float] = {}
    for name in buffers:
        if name not in schema.BY_NAME:
            raise StoreError(f"{path}: unknown buffer {name!r} (schema has {', '.join(schema.BY_NAME)})")
        buf = schema.BY_NAME[name]
        for key, names, dtype in ((name, buf.exr_channels, buf.dtype),
                                  (schema.variance_name(name), buf.variance_channels, np.float32)):
            if key in constants:
                for ch in names:
                    omitted[ch] = _round_to_storage(constants[key], dtype)
                continue
            if key not in arrays:
                raise StoreError(f"{path}: buffer {key!r} has neither data nor a constant")
            arr = np.asarray(arrays[key])
            if arr.ndim == 2:
                arr = arr[..., None]
            if arr.ndim != 3 or arr.shape[2] != buf.size:
                raise StoreError(f"{path}: buffer {key!r} has shape {arr.shape}, expected HxWx{buf.size}")
            if shape is None:
                shape = arr.shape[:2]
            elif arr.shape[:2] != shape:
                raise StoreError(f"{path}: buffer {key!r} is {arr.shape[:2]}, other buffers are {shape}")
            if not np.all(np.isfinite(arr)):
                raise StoreError(f"{path}: buffer {key!r} has non-finite values; repair (and count) them first")
            for c, ch in enumerate(names):
                data = np.ascontiguousarray(arr[..., c], dtype=dtype)
                value = constant_value(data) if omit_constant else None
                if value is not None:
                    omitted[ch] = value
                else:
                    channels[ch] = data
    if shape is None:
        raise StoreError(f"{path}: no buffer has pixel data, cannot tell the image size")
    if not channels:
        # OpenEXR needs at least one channel; keep the beauty's red even if constant.
        first = schema.BY_NAME[buffers[0]]
        ch = first.exr_channels[0]
        channels[ch] = np.full(shape, omitted.pop(ch), dtype=first.dtype)
    record = {
        "format": FORMAT, "version": FORMAT_VERSION, "buffers": buffers,
        "height": int(shape[0]), "width": int(shape[1]),
        "constants": dict(sorted(omitted.items())), **(meta or {}),
    }
    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        META_KEY: json.dumps(record, sort_keys=True, allow_nan=False),
    }

    def write(tmp: str) -> None:
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)

    atomic_write_bytes(Path(path), write)
    return record


def read_header(path: Path) -> dict:
    """The image's ``mcdenoise`` record, without reading pixels."""
    return _open(path, header_only=True)[0]


def _open(path: Path, header_only: bool = False):
    path = Path(path)
    if not path.exists():
        raise StoreError(f"{path}: image is missing")
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as exc:
        raise StoreError(f"{path}: cannot read ({exc.strerror})") from None
    if magic != b"\x76\x2f\x31\x01":
        raise StoreError(f"{path}: not an OpenEXR file (bad magic number)")
    try:
        f = OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
        header = f.header()
    except Exception as exc:  # OpenEXR raises ValueError/RuntimeError/IOError depending on the damage
        raise StoreError(f"{path}: corrupt or truncated EXR ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    raw = header.get(META_KEY)
    if not isinstance(raw, str):
        raise StoreError(f"{path}: header attribute {META_KEY!r} is missing: not an image written by this pipeline")
    try:
        record = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise StoreError(f"{path}: header attribute {META_KEY!r} is not valid JSON ({exc})") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise StoreError(f"{path}: header attribute {META_KEY!r} is not a {FORMAT} record")
    if record.get("version") != FORMAT_VERSION:
        raise StoreError(f"{path}: image format version {record.get('version')!r}, this code reads {FORMAT_VERSION}")
    h, w = record.get("height"), record.get("width")
    if not (isinstance(h, int) and isinstance(w, int) and 0 < h <= MAX_SIDE and 0 < w <= MAX_SIDE):
        raise StoreError(f"{path}: image size {w!r}x{h!r} is not a valid size (1..{MAX_SIDE})")
    (x0, y0), (x1, y1) = header["dataWindow"]
    if (int(y1 - y0 + 1), int(x1 - x0 + 1)) != (h, w):
        raise StoreError(f"{path}: data window {x1 - x0 + 1}x{y1 - y0 + 1} disagrees with the recorded {w}x{h}")
    return record, f, header


def read_image(path: Path, buffers: list[str] | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Read an image: ``{name: HxWxC float32, name.variance: ...}`` with constants restored.

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
        channels = f.channels()
    except Exception as exc:
        raise StoreError(f"{path}: corrupt or truncated EXR pixel data ({type(exc).__name__}: {exc})") from None
    out: dict[str, np.ndarray] = {}
    for name in wanted:
        buf = schema.BY_NAME[name]
        for key, names, dtype in ((name, buf.exr_channels, buf.dtype),
                                  (schema.variance_name(name), buf.variance_channels, np.float32)):
            arr = np.empty((h, w, buf.size), dtype=np.float32)
            for c, ch in enumerate(names):
                if ch in channels:
                    pix = channels[ch].pixels
                    if pix is None or pix.shape != (h, w):
                        raise StoreError(f"{path}: channel {ch!r} has shape "
                                         f"{None if pix is None else pix.shape}, expected {(h, w)}")
                    if pix.dtype != dtype:
                        raise StoreError(f"{path}: channel {ch!r} is {pix.dtype}, expected {np.dtype(dtype).name}")
                    arr[..., c] = pix
                elif ch in constants:
                    value = constants[ch]
                    if not isinstance(value, (int, float)) or not np.isfinite(value):
                        raise StoreError(f"{path}: constant for channel {ch!r} is {value!r}, expected a finite number")
                    arr[..., c] = value
                else:
                    raise StoreError(f"{path}: channel {ch!r} of buffer {name!r} is missing (neither stored nor a recorded constant)")
            out[key] = arr
    return out, record


def read_layers(path: Path) -> dict[str, np.ndarray]:
    """Buffers of *any* EXR that uses the schema's channel names (e.g. from another renderer).

    ``R, G, B`` are required; every other buffer (``albedo.R``…, ``N.X``…, ``variance.R``…) is
    read when all its channels are present and left out otherwise (consumers treat a missing
    feature as its background value). No ``mcdenoise`` header is needed.
    """
    path = Path(path)
    if not path.is_file():
        raise StoreError(f"{path}: EXR file not found")
    with open(path, "rb") as fh:
        if fh.read(4) != b"\x76\x2f\x31\x01":
            raise StoreError(f"{path}: not an OpenEXR file (bad magic number)")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            channels = {name: ch.pixels for name, ch in f.channels().items()}
    except Exception as exc:
        raise StoreError(f"{path}: corrupt or truncated EXR ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    if not all(c in channels for c in ("R", "G", "B")):
        raise StoreError(f"{path}: channels R, G, B (the noisy colour) are required; found {', '.join(sorted(channels))}")
    out: dict[str, np.ndarray] = {}
    shape = channels["R"].shape
    for buf in schema.BUFFERS:
        for key, names in ((buf.name, buf.exr_channels), (schema.variance_name(buf.name), buf.variance_channels)):
            if all(n in channels for n in names):
                arrs = [channels[n] for n in names]
                for n, a in zip(names, arrs):
                    if a.shape != shape:
                        raise StoreError(f"{path}: channel {n!r} has shape {a.shape}, expected {shape}")
                out[key] = np.stack(arrs, axis=2).astype(np.float32)
    return out
