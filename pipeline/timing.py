"""Wall-clock timing shared by the benchmarks (``make bench``: the dataset stage's and the denoiser's)."""
from __future__ import annotations

import time


def best_time(fn, repeats: int) -> float:
    """Best wall time of ``repeats`` calls of ``fn`` (seconds)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best
