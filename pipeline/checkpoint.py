"""Checkpoints and training curves shared by every trainer (cleaner, Isik baseline, AFGSA, diffusion, oidn_ft).

Everything is safetensors or JSON; nothing is pickled, so a checkpoint from elsewhere cannot run
code when it is loaded.

- ``save_safetensors``: tensors + string metadata, written atomically, with a CRC-32 of both in the
  metadata (``crc32``); ``read_safetensors``: tensors and metadata, the CRC checked where the file
  has one (safetensors itself has no checksum: a flipped bit in a weight would load silently).
- ``save_last`` / ``load_last``: the resumable state after a finished epoch in one file: a
  module's weights (``model.*``), the optimizer's moments (``optim.*``; several optimizers, a
  dict, under ``optim.<name>.*``), the torch RNG state and,
  in the metadata, a JSON record (epoch, history, optimizer hyper-parameters, ...). Loading
  restores all of it in place and returns the record.
- ``plot_curves``: named (x, y) series as a PNG (log y when every value is positive).
- ``NanGuard``: counts the optimisation steps skipped for a non-finite loss or gradient and stops
  the run after ``limit`` of them in a row.
"""
from __future__ import annotations

import json
import zlib
from pathlib import Path

import torch

from .errors import CheckpointError, StoreError
from .exr import atomic_write_bytes

CHECKSUM = "crc32"


def _crc32(tensors: dict[str, torch.Tensor], metadata: dict[str, str]) -> str:
    """CRC-32 of the metadata (but the checksum) and of every tensor's name, dtype, shape and bytes."""
    crc = zlib.crc32(json.dumps({k: v for k, v in metadata.items() if k != CHECKSUM}, sort_keys=True).encode())
    for name in sorted(tensors):
        t = tensors[name].detach().contiguous().cpu()
        crc = zlib.crc32(f"{name}|{t.dtype}|{list(t.shape)}".encode(), crc)
        crc = zlib.crc32(t.reshape(-1).view(torch.uint8).numpy().tobytes(), crc)
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


def _optimizers(opt) -> dict[str, torch.optim.Optimizer]:
    """One optimizer is stored under ``optim.``; several (a dict, e.g. a GAN's generator and critic)
    under ``optim.<name>.``, with their param groups under the same names in the record."""
    return opt if isinstance(opt, dict) else {"": opt}


def save_last(path: Path, model: torch.nn.Module, opt, record: dict, fmt: str,
              extra: dict[str, torch.Tensor] | None = None) -> None:
    """``opt``: an optimizer, or a dict name → optimizer."""
    tensors = {f"model.{k}": v for k, v in model.state_dict().items()}
    groups = {}
    for name, o in _optimizers(opt).items():
        sd = o.state_dict()
        prefix = f"optim.{name}." if name else "optim."
        for idx, state in sd["state"].items():
            for key, value in state.items():
                tensors[f"{prefix}{idx}.{key}"] = torch.as_tensor(value)
        groups[name] = sd["param_groups"]
    tensors["rng.torch"] = torch.get_rng_state()
    tensors.update({f"extra.{k}": v for k, v in (extra or {}).items()})
    record = {**record, "param_groups": groups if isinstance(opt, dict) else groups[""]}
    save_safetensors(path, tensors, {"format": fmt, "state": json.dumps(record, allow_nan=False)})


def load_last(path: Path, model: torch.nn.Module, opt, device,
              extra: dict[str, torch.Tensor] | None = None, fingerprint: dict | None = None) -> dict:
    """Restore ``model``, ``opt``, the torch RNG (and fill ``extra`` with saved extras); return the record.

    ``fingerprint``: the settings the checkpoint must have been made with. Checked before any
    weight is loaded, so a run with another model shape gets the list of changed settings, not
    a tensor size mismatch."""
    tensors, metadata = read_safetensors(path, "a checkpoint this trainer wrote", "delete it to start over")
    try:
        record = json.loads(metadata["state"])
        if not isinstance(record, dict):
            raise ValueError(f"a JSON {type(record).__name__}")
    except (KeyError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a checkpoint this trainer wrote (no state record: {exc}); "
                              "delete it to start over") from None
    start_over = f"delete {Path(path).parent} or set another 'runs' folder to start over"
    if fingerprint is not None and record.get("fingerprint") != fingerprint:
        old = record.get("fingerprint") or {}
        changed = sorted(k for k in set(fingerprint) | set(old) if old.get(k) != fingerprint.get(k))
        raise CheckpointError(f"{path}: made with different settings ({', '.join(changed)}); {start_over}")
    try:
        model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[0]
        raise CheckpointError(f"{path}: made for a different model ({first}); {start_over}") from None
    for name, o in _optimizers(opt).items():
        prefix = f"optim.{name}." if name else "optim."
        state: dict[int, dict] = {}
        for k, v in tensors.items():
            if k.startswith(prefix):
                idx, key = k[len(prefix):].split(".", 1)
                state.setdefault(int(idx), {})[key] = v if key == "step" else v.to(device)
        saved = record["param_groups"][name] if isinstance(opt, dict) else record["param_groups"]
        groups = [{**g, "betas": tuple(g["betas"])} if "betas" in g else g for g in saved]
        o.load_state_dict({"state": state, "param_groups": groups})
    torch.set_rng_state(tensors["rng.torch"])
    if extra is not None:
        extra.update({k[6:]: v for k, v in tensors.items() if k.startswith("extra.")})
    return record


class NanGuard:
    """``ok(finite, epoch, step)``: True for a finite step; a non-finite one is counted (``skipped``)
    and returns False, so the caller skips its update; ``limit`` of them in a row raise ``error``."""

    def __init__(self, name: str, limit: int, error: type[Exception] = StoreError):
        self.name, self.limit, self.error = name, int(limit), error
        self.skipped = self.in_row = 0

    def ok(self, finite: bool, epoch: int, step: int) -> bool:
        if finite:
            self.in_row = 0
            return True
        self.skipped += 1
        self.in_row += 1
        if self.in_row >= self.limit:
            raise self.error(f"{self.name}: {self.in_row} steps in a row had a non-finite loss or gradient "
                             f"(epoch {epoch + 1}, step {step}); check the data (python -m pipeline inspect) "
                             "or lower the learning rate")
        return False


def plot_curves(path: Path, curves: dict[str, list[tuple[float, float]]], title: str, xlabel: str = "epoch",
                ylabel: str = "loss", right: dict[str, list[tuple[float, float]]] | None = None,
                right_label: str = "") -> None:
    """Named (x, y) series as a PNG, written atomically; ``right`` series get their own y axis."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    values = []
    for name, pts in curves.items():
        if pts:
            ax.plot(*zip(*pts), "o-" if len(pts) < 60 else "-", label=name, markersize=3)
            values += [y for _, y in pts]
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if values and all(v > 0 for v in values):
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if right:
        ax2 = ax.twinx()
        for i, (name, pts) in enumerate(right.items()):
            if pts:
                ax2.plot(*zip(*pts), "s--" if i == 0 else ":", color=f"C{3 + i}", label=name, markersize=3)
        ax2.set_ylabel(right_label)
        h2, l2 = ax2.get_legend_handles_labels()
        handles, labels = handles + h2, labels + l2
    ax.set_title(title)
    ax.legend(handles, labels)
    fig.tight_layout()
    atomic_write_bytes(path, lambda tmp: fig.savefig(tmp, format="png"))
