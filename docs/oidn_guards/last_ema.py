"""A model folder from a Control Module run's last epoch (its EMA weights), for scoring beside the best epoch.

A run keeps the epoch that validated best (``control.safetensors``) and its last state (``last.safetensors``:
EMA, optimiser, RNG). When the best epoch is epoch 0 (the model it started from), what the training did is
only in the last state; this writes it as a folder ``realizations.py`` reads (``runs=OUT``):

    python docs/oidn_guards/last_ema.py runs/ship_sun_S/diffusion_sppany /tmp/S60/diffusion_sppany
"""
import shutil
import sys
from pathlib import Path

from safetensors import safe_open

from mcdenoise.pipeline.weights import save_safetensors
from mcdenoise.train import model as oidn_refine


def main(run: Path, out: Path) -> None:
    model, _ = oidn_refine.load(run)
    names = [n for n, _ in model.control.named_parameters()]   # the EMA's order: the module's parameters
    with safe_open(str(run / "last.safetensors"), "pt") as f:
        keys = set(f.keys())
        if f"extra.ema.{len(names)}" in keys or f"extra.ema.{len(names) - 1}" not in keys:
            raise SystemExit(f"{run / 'last.safetensors'}: expected {len(names)} EMA tensors")
        state = {n: f.get_tensor(f"extra.ema.{i}").contiguous() for i, n in enumerate(names)}
    for n, p in model.control.named_parameters():
        if p.shape != state[n].shape:
            raise SystemExit(f"{n}: EMA shape {tuple(state[n].shape)}, model {tuple(p.shape)}")
    out.mkdir(parents=True, exist_ok=True)
    for name in ("base.tza", "model.json"):
        shutil.copy(run / name, out / name)
    with safe_open(str(run / "control.safetensors"), "pt") as f:
        meta = f.metadata()
    save_safetensors(out / "control.safetensors", state, meta)   # a new CRC-32 for the new tensors
    print(f"{out}: the last epoch's EMA weights ({len(names)} tensors)")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
