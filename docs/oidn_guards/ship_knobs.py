"""Variants of the shipped denoiser that need no training: how far its base moves from OIDN, how
loud its Control Module speaks.

The base moves as ``python -m pipeline export --from M --base-blend B`` moves it (``train.export.rebase``:
OIDN + B × what fine-tuning changed). The Control Module reaches OIDN's decoder only through its zero
1×1 convolutions, and the decoder adds their outputs to its skips, so scaling those convolutions'
weights and biases by ``c`` scales what it adds by ``c``; ``c = 0`` is the base alone.

    python docs/oidn_guards/ship_knobs.py OUT_RUNS --base-blend 0.45 --control 0.8 [--model train/shipped]
        → OUT_RUNS/diffusion_sppany, read by `ours` with the override runs=OUT_RUNS
"""
import argparse
import json
from pathlib import Path

from mcdenoise.pipeline import weights
from mcdenoise.train.export import rebase

SHIPPED = Path(__file__).resolve().parents[2] / "train" / "shipped"


def make(out_runs: Path, base_blend: float, control: float, model: Path = SHIPPED) -> Path:
    folder = rebase(model, base_blend, Path(out_runs) / "diffusion_sppany", quiet=True)
    if control != 1.0:
        meta = json.loads((folder / "model.json").read_text())
        state = weights.load_tensors(folder / "control.safetensors")
        state = {k: (v * control if k.startswith("zero.") else v) for k, v in state.items()}
        weights.save(folder, "oidn_control", state, {**meta, "control_scale": control}, weights="control.safetensors")
    return folder


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("out_runs", type=Path)
    ap.add_argument("--base-blend", type=float, required=True)
    ap.add_argument("--control", type=float, default=1.0)
    ap.add_argument("--model", type=Path, default=SHIPPED)
    a = ap.parse_args()
    print(make(a.out_runs, a.base_blend, a.control, a.model))
