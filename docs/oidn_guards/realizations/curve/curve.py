"""The training curve of the shipped Control Module trained on: validation gain against megapixels trained.

    python docs/oidn_guards/realizations/curve/curve.py RUN/train.json OUT_DIR [--crop 64] [--batch 8]
        [--start-mpix 41.9]

Reads the trainer's per-epoch validation (ship val, strength 1, gain over the base at each spp; epoch 0 is
the starting model) and writes ``curve.png`` and ``curve.md`` (the table) into OUT_DIR.
"""
import argparse
import json
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def rows(history: list, crop: int, batch: int, start: float) -> list[dict]:
    """One row per validated epoch: megapixels trained in all (``start`` before the run) and the gains."""
    out, steps = [], 0
    for h in history:
        steps += h.get("steps", 0) - h.get("skipped_steps", 0)
        if h.get("val"):
            out.append({"epoch": h["epoch"], "mpix": start + steps * batch * crop * crop / 1e6, "lr": h.get("lr", 0.0),
                        **{k: v for k, v in h["val"].items() if k.startswith("gain_spp")}})
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("train_json")
    ap.add_argument("out")
    ap.add_argument("--crop", type=int, default=64)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--start-mpix", type=float, default=41.9, help="what the starting model had seen")
    a = ap.parse_args()
    history = json.loads(Path(a.train_json).read_text())["history"]
    table = rows(history, a.crop, a.batch, a.start_mpix)
    keys = sorted({k for r in table for k in r if k.startswith("gain_spp")}, key=lambda k: int(k[8:]))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(7, 4), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for k in keys:
        ax.plot([r["mpix"] for r in table], [r[k] for r in table], "o-", markersize=3, label=f"{k[8:]} spp")
    ax.set_xlabel("megapixels trained (64² crops; the shipped model: 42)")
    ax.set_ylabel("ship val: gain over the base (dB)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    ax.set_title("Control Module trained on from the shipped model (strength 1)")
    fig.savefig(out / "curve.png", bbox_inches="tight")
    lines = ["| epoch | Mpix trained | × shipped | lr | " + " | ".join(f"gain {k[8:]} spp (dB)" for k in keys) + " |",
             "| ---: | ---: | ---: | ---: |" + " ---: |" * len(keys)]
    lines += [f"| {r['epoch']} | {r['mpix']:.0f} | {r['mpix'] / a.start_mpix:.1f} | {r['lr']:.2e} | "
              + " | ".join(f"{r.get(k, float('nan')):+.3f}" for k in keys) + " |" for r in table]
    (out / "curve.md").write_text("\n".join(lines) + "\n")
    print(f"{out}: {len(table)} validated epochs, up to {table[-1]['mpix']:.0f} Mpix" if table else "no validated epoch")


if __name__ == "__main__":
    main()
