"""The resumable state of a training run (``last.safetensors``), shared by every trainer (cleaner, Isik
baseline, AFGSA, diffusion, oidn_ft).

Everything is safetensors (``pipeline.weights``' writer, with its CRC-32) or JSON; nothing is pickled, so
a checkpoint from elsewhere cannot run code when it is loaded.

- ``save_last`` / ``load_last``: the resumable state after a finished epoch in one file: a
  module's weights (``model.*``), the optimizer's moments (``optim.*``; several optimizers, a
  dict, under ``optim.<name>.*``), the torch RNG state and,
  in the metadata, a JSON record (epoch, history, optimizer hyper-parameters, ...). Loading
  restores all of it in place and returns the record.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch

from .errors import CheckpointError
from .weights import read_safetensors, save_safetensors


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
