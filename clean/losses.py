"""Training losses of the cleaner and the Isik baseline.

The formulas live in ``pipeline.metrics`` (one definition for training and evaluation); this
module names the ones the trainers use and fixes their conventions.
"""
from __future__ import annotations

from pipeline.metrics import SMAPE_EPS, l1, smape

__all__ = ["smape", "l1", "SMAPE_EPS"]
