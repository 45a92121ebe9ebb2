"""Metric cells of two evaluation reports, frame by frame: how many (group, spp, method, frame, metric)
cells both have, how many are equal, and the largest difference. Timing columns are left out.

    python docs/refactor_check/compare_reports.py REPORT_A REPORT_B     (folders with eval_frames.csv)
"""
import csv
import sys
from pathlib import Path

METRICS = ("l1", "psnr", "ssim", "flip", "hdr_flip", "fvvdp", "mc_spp", "status")


def cells(folder: Path) -> dict:
    with open(folder / "eval_frames.csv", newline="") as f:
        return {(r["group"], r["spp"], r["method"], r["frame"], m): r[m] for r in csv.DictReader(f) for m in METRICS
                if m in r}


if __name__ == "__main__":
    a, b = cells(Path(sys.argv[1])), cells(Path(sys.argv[2]))
    common = sorted(set(a) & set(b))
    differ = [k for k in common if a[k] != b[k]]
    methods = sorted({k[2] for k in common})
    print(f"{len(common)} cells in both ({len(methods)} methods: {', '.join(methods)}); {len(differ)} differ "
          f"(methods: {', '.join(sorted({k[2] for k in differ})) or 'none'}); only in A: {len(set(a) - set(b))}, "
          f"only in B: {len(set(b) - set(a))}")
    timed = [k for k in common if not k[2].startswith("mc_equal")]   # equal-time MC follows measured seconds
    print(f"without the equal-time MC rows: {len(timed)} cells, {sum(a[k] != b[k] for k in timed)} differ")
