"""The statistics of one table (a group of frames at one spp), from its per-frame scores.

``annotate(entry, ...)`` adds to every row of an evaluator entry (``entry["methods"]`` and the
equal-time MC rows ``entry["equal_time"]``):

- ``ci[metric]``: the mean over frames with its 95 % t interval (``stats.mean_ci``);
- ``vs[ref][metric]`` for ``ref`` in ``REFERENCES`` (OIDN as called by default, OIDN in its final-frame
  mode with prefiltered aux, and the noisy input, each where it is a row): the mean per-frame
  difference row − ref with its paired bootstrap 95 % interval (``stats.paired_bootstrap``),
  over the frames both have scores for;

and to the entry ``leads[metric]``: the best real denoiser by mean, the runner-up, and whether the
lead is significant (``stats.lead``). Real denoisers are the available methods except the noisy
input; equal-time MC rows are not denoisers and never lead.
"""
from __future__ import annotations

from .methods import parse
from .scoring import METRICS
from .stats import lead, mean_ci, paired_bootstrap, paired_values

REFERENCES = ("oidn", "oidn_prefilter", "noisy")


def frame_values(row: dict, metric: str) -> dict[str, float]:
    """{frame: value} of one row's frames that were scored."""
    return {p["frame"]: p["metrics"][metric] for p in row.get("per_frame", []) if "metrics" in p}


def scored_rows(entry: dict) -> dict[str, dict]:
    """Rows with per-frame scores: available methods, then equal-time MC as ``mc_equal_<method>``."""
    rows = {n: r for n, r in entry["methods"].items() if r["available"]}
    rows.update({f"mc_equal_{n}": et for n, et in entry.get("equal_time", {}).items()})
    return rows


def denoisers(entry: dict) -> list[str]:
    return [n for n, r in entry["methods"].items() if r["available"] and parse(n).family != "noisy"]


def annotate(entry: dict, metric_names: list[str], resamples: int, seed: int) -> None:
    rows = scored_rows(entry)
    for name, row in rows.items():
        row["ci"] = {m: mean_ci(list(frame_values(row, m).values())) for m in metric_names}
        row["vs"] = {ref: {m: paired_bootstrap(*paired_values(frame_values(row, m), frame_values(rows[ref], m)),
                                               resamples, seed) for m in metric_names}
                     for ref in REFERENCES if ref in rows and ref != name}
    entry["leads"] = {m: lead({n: frame_values(rows[n], m) for n in denoisers(entry)}, METRICS[m].higher_is_better,
                              resamples, seed) for m in metric_names}
