"""The training curve of the shipped Control Module trained on: validation gain against megapixels trained.

    python docs/oidn_guards/realizations/curve/curve.py RUN/train.json [RUN2/train.json ...] OUT_DIR [--crop 64]
        [--batch 8] [--start-mpix 41.9] [--scored e0=42 e16=84]

Reads the trainer's per-epoch validation (ship val, strength 1, gain over the base at each spp; epoch 0 is
the starting model); several runs are one curve when each started from the one before's last epoch (a later
run's epoch 0 is that epoch again, read back from its folder: it is checked to validate within 0.01 dB of it
and left out). Writes ``curve.png`` and ``curve.md`` (the table) into OUT_DIR. ``--scored
LABEL=MPIX``: snapshots scored by ``realizations.py --json`` into OUT_DIR/LABEL_default_val.json and
LABEL_val9.json, drawn beside the curve (mean gain over the scenes at 4 spp, every realization).
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


def chained(histories: list[list], crop: int, batch: int, start: float) -> list[dict]:
    """The rows of runs trained one after the other; epochs numbered from the first run's start."""
    table: list[dict] = []
    for history in histories:
        part = rows(history, crop, batch, table[-1]["mpix"] if table else start)
        if table:
            head = part.pop(0)
            if head["epoch"] != 0 or any(abs(head[k] - table[-1][k]) > 0.01 for k in head if k.startswith("gain_spp")):
                raise SystemExit(f"a run does not start where the one before ended: {head} after {table[-1]}")
            for r in part:
                r["epoch"] += table[-1]["epoch"]
        table += part
    return table


def scored_gain(path: Path, method: str, spp: str = "4", reference: str = "oidn_prefilter") -> float:
    """The mean over scenes of each scene's mean gain over its realizations (what realizations.py prints)."""
    scenes = json.loads(path.read_text())[spp]
    gains = [sum(a - b for a, b in zip(r[method], r[reference])) / len(r[reference]) for r in scenes.values()]
    return sum(gains) / len(gains)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("train_json", nargs="+", help="train.json of each run, in the order they were trained")
    ap.add_argument("out")
    ap.add_argument("--crop", type=int, default=64)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--start-mpix", type=float, default=41.9, help="what the starting model had seen")
    ap.add_argument("--scored", nargs="*", default=[], help="LABEL=MPIX of snapshots scored into OUT_DIR")
    a = ap.parse_args()
    table = chained([json.loads(Path(p).read_text())["history"] for p in a.train_json], a.crop, a.batch, a.start_mpix)
    keys = sorted({k for r in table for k in r if k.startswith("gain_spp")}, key=lambda k: int(k[8:]))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    scored = [(x.split("=")[0], float(x.split("=")[1])) for x in a.scored]
    fig = Figure(figsize=(13 if scored else 7, 4), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2 if scored else 1, 1)
    for k in keys:
        ax.plot([r["mpix"] for r in table], [r[k] for r in table], "o-", markersize=3, label=f"{k[8:]} spp")
    ax.set_xlabel("megapixels trained (64² crops; the shipped model: 42)")
    ax.set_ylabel("ship val: gain over the base (dB)")
    ax.grid(True, alpha=0.3)
    ax.legend()
    ax.set_title("Trained on from the shipped model: ship val, strength 1", fontsize=10)
    if scored:
        bx = fig.add_subplot(1, 2, 2)
        for data, style in (("default_val", "o-"), ("val9", "s--")):
            for method, strength in (("ours_strength50", "0.5"), ("ours_strength100", "1")):
                bx.plot([m for _, m in scored], [scored_gain(out / f"{lab}_{data}.json", method) for lab, _ in scored],
                        style, label=f"{'default val' if data == 'default_val' else 'nine val_* scenes'}, strength {strength}")
        bx.axhline(0, color="k", lw=0.6)
        bx.set_xlabel("megapixels trained")
        bx.set_ylabel("4 spp: gain over the base (dB)")
        bx.grid(True, alpha=0.3)
        bx.legend(fontsize=8)
        bx.set_title("Scored, every noise realization: the generator's scenes and hand-made ones", fontsize=10)
    fig.savefig(out / "curve.png", bbox_inches="tight")
    lines = ["| epoch | Mpix trained | × shipped | lr | " + " | ".join(f"gain {k[8:]} spp (dB)" for k in keys) + " |",
             "| ---: | ---: | ---: | ---: |" + " ---: |" * len(keys)]
    lines += [f"| {r['epoch']} | {r['mpix']:.0f} | {r['mpix'] / a.start_mpix:.1f} | {r['lr']:.2e} | "
              + " | ".join(f"{r.get(k, float('nan')):+.3f}" for k in keys) + " |" for r in table]
    (out / "curve.md").write_text("\n".join(lines) + "\n")
    print(f"{out}: {len(table)} validated epochs, up to {table[-1]['mpix']:.0f} Mpix" if table else "no validated epoch")


if __name__ == "__main__":
    main()
