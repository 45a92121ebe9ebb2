"""Paired differences between two rows of a report (the report pairs every row with `oidn` only).

    python docs/oidn_guards/paired_rows.py docs/example_report/eval_frames.csv oidn_ft_albedo oidn_albedo

Per spp of the test group: the mean over frames of (A − B) for PSNR, HDR-FLIP and FLIP, a paired
bootstrap 95 % interval (4 000 resamples of the frames, seed 0) and how many frames A is better on.
"""
import csv
import sys

import numpy as np


def main(path: str, a: str, b: str, group: str = "test") -> None:
    rows = [r for r in csv.DictReader(open(path)) if r["group"] == group and r["status"] == "ok"]
    rng = np.random.default_rng(0)
    for spp in sorted({r["spp"] for r in rows}, key=int):
        A = {r["frame"]: r for r in rows if r["method"] == a and r["spp"] == spp}
        B = {r["frame"]: r for r in rows if r["method"] == b and r["spp"] == spp}
        out = []
        for m, higher_better in (("psnr", True), ("hdr_flip", False), ("flip", False)):
            d = np.array([float(A[f][m]) - float(B[f][m]) for f in A])
            boot = [rng.choice(d, len(d)).mean() for _ in range(4000)]
            better = int(((d > 0) if higher_better else (d < 0)).sum())
            out.append(f"{m} {d.mean():+.4f} [{np.percentile(boot, 2.5):+.4f}, {np.percentile(boot, 97.5):+.4f}] "
                       f"better on {better}/{len(d)}")
        print(f"{a} − {b}, {group}, {spp} spp: " + "; ".join(out))


if __name__ == "__main__":
    main(*sys.argv[1:])
