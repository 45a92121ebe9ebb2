"""The temporal filter's history clamp: the 3x3 min-max box against variance clipping (docs/sequences.md, "The
history's clamp", has the rule this measures for).

    python docs/experiments/history_clamp.py --store data/sequence --split val
    python docs/experiments/history_clamp.py --store data/val_seq --split external

Per sequence of the split and per spp: OIDN's final-frame output of every frame (``oidn_prefilter``, the first
noise realization), then the temporal filter along the sequence with each clamp, as ``pipeline.temporal.step``
runs it (the history warped with the noisy input's depth and normal, weight on the new frame), reading the
history bilinearly except for "cubic" (Catmull-Rom, what ``motion.warp_previous`` reads with). Prints, per clamp
and spp, the mean over sequences of (mean over t >= 1 of PSNR - oidn_prefilter's), the mean over the two spp,
and the sequences below oidn_prefilter.
"""
from __future__ import annotations

import argparse

import numpy as np

from mcdenoise.evaluate.run import _reference_name, realization_stacks
from mcdenoise.evaluate.scoring import score
from mcdenoise.evaluate.sequence import read_frame, sequences
from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.store import Store
from mcdenoise.train import oidn


def variance_box(current: np.ndarray, gamma: float) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel and channel, mean -/+ gamma standard deviations of the 3x3 neighbourhood, inside its min-max."""
    h, w = current.shape[:2]
    pad = np.pad(current.astype(np.float64), ((1, 1), (1, 1), (0, 0)), mode="edge")
    windows = np.stack([pad[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)])
    mu, sigma = windows.mean(axis=0), windows.std(axis=0)
    lo, hi = temporal.neighbourhood_range(current)
    return np.maximum(mu - gamma * sigma, lo).astype(np.float32), np.minimum(mu + gamma * sigma, hi).astype(np.float32)


def blend(current, history, valid, weight, gamma):
    """``temporal.blend_history`` with the history clamped to the min-max box (gamma None or "cubic") or the
    variance box."""
    if gamma is None or gamma == "cubic":
        return temporal.blend_history(current, history, valid, weight)
    lo, hi = variance_box(current, gamma)
    return temporal.blend_history(current, np.clip(history, lo, hi), valid, weight, clamp=False)


def arguments(doc: str) -> argparse.ArgumentParser:
    """The options both history experiments take (this one and history_sources.py)."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--store", required=True)
    ap.add_argument("--split", required=True)
    ap.add_argument("--spp", default="4,16")
    ap.add_argument("--weight", type=float, default=0.7)
    return ap


def oidn_sequences(store: Store, split: str, spp: int):
    """(name, frames, OIDN's final-frame output of each) of every sequence of ``split`` at ``spp``, the first noise
    realization, against GT1 where an external scene has no gt_clean."""
    for name, seq in sequences(store.frames(split)).items():
        ref = _reference_name(store, seq[0], split == "external")
        frames = [read_frame(store, k, spp, realization_stacks(store, k, spp, 1)[0], ref) for k in seq]
        yield name, frames, [oidn.denoise({k: f.buffers[k] for k in ("color", "albedo", "normal")}, aux=True,
                                          clean_aux=True) for f in frames]


def main() -> int:
    ap = arguments(__doc__)
    ap.add_argument("--gammas", default="minmax,1,1.5",
                    help="minmax, a variance-clipping gamma, or cubic (Catmull-Rom resampling, min-max clamp)")
    args = ap.parse_args()
    store = Store(args.store)
    clamps = {g: None if g == "minmax" else g if g == "cubic" else float(g) for g in args.gammas.split(",")}
    seqs = sequences(store.frames(args.split))
    gains: dict[str, dict[int, dict[str, float]]] = {c: {} for c in clamps}
    spps = [int(s) for s in args.spp.split(",")]
    for spp in spps:
        for name, frames, base in oidn_sequences(store, args.split, spp):
            base_psnr = [score(y, f.reference, ["psnr"])["psnr"] for y, f in zip(base, frames)]
            for clamp, gamma in clamps.items():
                out = [base[0]]
                for t in range(1, len(frames)):
                    # the history read bilinearly, or with Catmull-Rom ("cubic", what motion.warp_previous reads with)
                    xy, valid = motion.reproject_view(frames[t].views["input"], frames[t - 1].views["input"])
                    kernel = "catmull_rom" if gamma == "cubic" else "bilinear"
                    history = motion.warp(out[t - 1], xy, valid, kernel=kernel), valid
                    out.append(blend(base[t], *history, args.weight, gamma))
                psnr = [score(y, f.reference, ["psnr"])["psnr"] for y, f in zip(out, frames)]
                gains[clamp].setdefault(spp, {})[name] = float(np.mean(np.subtract(psnr[1:], base_psnr[1:])))
            print(f"{spp} spp {name}: " + ", ".join(f"{c} {gains[c][spp][name]:+.3f}" for c in clamps), flush=True)
    print(f"\n{args.store} {args.split}: {len(seqs)} sequences, weight {args.weight:g}, t >= 1, "
          "PSNR gain over oidn_prefilter (mean over sequences)")
    print("| clamp | " + " | ".join(f"{s} spp" for s in spps) + " | mean | sequences below, " + " / ".join(map(str, spps))
          + " spp |")
    print("| --- |" + " ---: |" * (len(spps) + 1) + " --- |")
    for c in clamps:
        per = [float(np.mean(list(gains[c][s].values()))) for s in spps]
        below = [sum(v < 0 for v in gains[c][s].values()) for s in spps]
        print(f"| {c} | " + " | ".join(f"{v:+.3f}" for v in per) + f" | {np.mean(per):+.3f} | "
              + " / ".join(map(str, below)) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
