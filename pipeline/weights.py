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

The resumable state of a run (``last.safetensors``) is ``pipeline.checkpoint``'s; OIDN's own weight
format, ``pipeline.tza``'s; where each model's run lives and which run serves a sample count,
``pipeline.runs``'; ``train.export`` makes self-contained model folders of these.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

from .checkpoint import read_safetensors, save_safetensors
from .errors import CheckpointError
from .exr import atomic_write_json, read_json

# kind -> format tag (written into both files; the tags are what runs on disk already carry)
FORMATS = {
    "affinity": "mcdenoise-affinity",          # the GT cleaner and the Isik baseline (clean.model)
    "afgsa": "mcdenoise-afgsa",                # AFGSA (train.afgsa)
    "oidn_control": "mcdenoise-oidn-control",  # the diffusion denoiser: a Control Module on OIDN's network (train.model)
    "oidn_ft": "mcdenoise-oidn-ft",            # OIDN's network fine-tuned (train.oidn_ft)
}
RECORD = "model.json"


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
