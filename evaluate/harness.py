"""Run one method on one frame: repair the inputs, time the call, check the output.

NaN/Inf in the inputs are repaired explicitly and counted (``pipeline.numerics.repair_nonfinite``:
replaced by 0, as the renderer does before it stores an image) on a copy, before any method
sees them, so every method gets the same finite inputs and the count is reported. A method's
output is checked, not fixed: wrong shape, exceptions and non-finite values are reported as
such; ``finite_output`` gives the metrics a repaired copy and the count of what was repaired.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mcdenoise.pipeline.numerics import repair_nonfinite

from .methods import Method


@dataclass
class Outcome:
    output: np.ndarray | None          # (H, W, 3) float32 as the method returned it, None on error
    seconds: float                     # wall time of denoise() alone
    input_repaired: dict = field(default_factory=dict)   # buffer key -> NaN/Inf values set to 0
    output_nonfinite: int = 0
    error: str | None = None           # exception or wrong shape; output is None then
    note: str = ""                     # what the method says it did beyond denoising (Method.note)

    @property
    def ok(self) -> bool:
        return self.error is None and self.output_nonfinite == 0

    def status(self) -> str:
        if self.error:
            return f"error: {self.error}"
        if self.output_nonfinite:
            return f"{self.output_nonfinite} non-finite output values"
        return "ok"


def repaired_inputs(buffers: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """A float32 copy of ``buffers`` with NaN/±Inf set to 0, and the count per key."""
    out = {k: np.array(v, dtype=np.float32) for k, v in buffers.items()}
    return out, repair_nonfinite(out)


def run_method(method: Method, buffers: dict[str, np.ndarray], history: tuple | None = None) -> Outcome:
    """``history``: (the previous output warped into this frame, its validity) for a method that reads it."""
    clean, counts = repaired_inputs(buffers)
    shape = clean["color"].shape[:2] + (3,)
    t0 = time.perf_counter()
    try:
        out = method.denoise(clean) if history is None else method.denoise(clean, history=history)
    except Exception as exc:  # a method's failure is a result to report, not a crash of the run
        return Outcome(None, time.perf_counter() - t0, counts, 0, f"{type(exc).__name__}: {exc}".strip())
    seconds = time.perf_counter() - t0
    out = np.asarray(out)
    if out.shape != shape:
        return Outcome(None, seconds, counts, 0, f"output shape {out.shape}, expected {shape}")
    out = out.astype(np.float32, copy=False)
    return Outcome(out, seconds, counts, int((~np.isfinite(out)).sum()), note=method.note())


def finite_output(outcome: Outcome) -> np.ndarray:
    """The output with non-finite values set to 0 (counted in ``outcome.output_nonfinite``)."""
    out = outcome.output.copy()
    out[~np.isfinite(out)] = 0.0
    return out
