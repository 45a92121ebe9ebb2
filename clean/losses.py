"""Training losses of the cleaner and the Isik baseline.

The image metrics live in ``pipeline.metrics`` (one definition for training and evaluation); this
module names the ones the trainers use: SMAPE (paper eq. 2) and L1.
"""
from __future__ import annotations

from mcdenoise.pipeline.metrics import SMAPE_EPS, l1, smape

__all__ = ["smape", "l1", "SMAPE_EPS"]
