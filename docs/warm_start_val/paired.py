"""Paired bootstrap 95 % interval of the per-frame PSNR difference new − old of the `ours` rows of two
evaluations of the same frames (python docs/warm_start_val/paired.py OLD_DIR NEW_DIR)."""
import csv
import sys

import numpy as np


def ours(folder):
    return {(r["spp"], r["frame"]): float(r["psnr"]) for r in csv.DictReader(open(f"{folder}/eval_frames.csv"))
            if r["method"] == "ours" and r["status"] == "ok"}


old, new = ours(sys.argv[1]), ours(sys.argv[2])
rng = np.random.default_rng(0)
for spp in sorted({k[0] for k in old}, key=int):
    d = np.array([new[k] - old[k] for k in old if k[0] == spp])
    boot = rng.choice(d, (5000, len(d))).mean(1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    print(f"{sys.argv[2]} vs {sys.argv[1]}, {spp} spp: {d.mean():+.3f} [{lo:+.3f}, {hi:+.3f}]{'*' if lo > 0 or hi < 0 else ''}"
          f" (n={len(d)}, better on {int((d > 0).sum())})")
