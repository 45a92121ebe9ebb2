"""The sequence page of a report (``sequence.md``): tables, per-frame curves and an animated strip.

Per group and spp one table: each method's frame 1 and frames 2.. apart (frame 1 has no frame before
it; with the frames after read, its input and its filter's history come from those alone), PSNR with the
paired difference to ``oidn_prefilter`` on frames 2.., L1, HDR-FLIP, the temporal instability and its ratio
to ``oidn_prefilter``'s, FovVideoVDP of the sequences as videos, seconds per frame. The paired interval
resamples *scenes* (each scene's mean over its frames 2..): the frames of one camera move share the scene and
are not independent.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from mcdenoise.pipeline.figures import animated_strip, plot_curves
from mcdenoise.pipeline.temporal import describe_averaging

from .report import fmt, fmt_diff, fmt_seconds, markdown_table, write_text
from .scoring import METRICS
from .sequence import SEQUENCE_METRICS
from .stats import MIN_FRAMES, paired_bootstrap, paired_values

REFERENCE = "oidn_prefilter"
STRIP = ("noisy", "oidn_prefilter", "oidn_prefilter_temporal", "ours", "ours_filter", "ours_temporal")


def scene_means(row: dict, metric: str) -> dict[str, float]:
    """{scene: mean over its frames 2.. of ``metric``} of one method's row."""
    by_scene: dict[str, list[float]] = {}
    for rec in row.get("per_frame", []):
        value = rec.get("metrics", {}).get(metric)
        if rec["index"] > 0 and value is not None and np.isfinite(value):
            by_scene.setdefault(rec["frame"].split("/")[0], []).append(value)
    return {s: float(np.mean(v)) for s, v in by_scene.items()}


def sequence_table(entry: dict, resamples: int, seed: int) -> list[str]:
    rows = entry["methods"]
    ref = rows.get(REFERENCE, {})
    ref_instability = ref.get("mean", {}).get("later", {}).get("instability") if ref.get("available") else None
    # PSNR has columns of its own (frame 1, frames 2.., the paired difference)
    metrics = [m for m in SEQUENCE_METRICS if m != "psnr" and m in entry["metrics"]]
    header = ["method", "PSNR frame 1", "PSNR frames 2..", f"Δ PSNR vs `{REFERENCE}` (2..)",
              *[f"{METRICS[m].column} (2..)" for m in metrics], "instability ↓ (2..)", f"÷ `{REFERENCE}`'s",
              "FovVideoVDP (video)", "s/frame"]
    table = []
    for name, row in rows.items():
        if not row["available"]:
            table.append([f"`{name}`", f"not available: {row['reason']}"] + [""] * (len(header) - 2))
            continue
        first, later = row["mean"]["first"], row["mean"]["later"]
        diff = None
        if name != REFERENCE and ref.get("available"):
            diff = paired_bootstrap(*paired_values(scene_means(row, "psnr"), scene_means(ref, "psnr")), resamples, seed)
        videos = [v for v in row["video"].values() if v is not None]
        ratio = (later["instability"] / ref_instability if ref_instability and later["instability"] is not None
                 else None)
        table.append([f"`{name}`", fmt("psnr", first["psnr"]), fmt("psnr", later["psnr"]),
                      fmt_diff("psnr", diff, "scenes") if diff else "", *[fmt(m, later[m]) for m in metrics],
                      fmt("l1", later["instability"]), f"{ratio:.2f}" if ratio is not None else "",
                      fmt("fvvdp", float(np.mean(videos))) if videos else "–",
                      fmt_seconds(float(np.mean([r["seconds"] for r in row["per_frame"]])))])
    return markdown_table(header, table)


def per_frame_curves(entry: dict, metric: str) -> dict[str, list[tuple[float, float]]]:
    """{method: [(frame number, mean over scenes)]} for the curve plot."""
    curves = {}
    for name, row in entry["methods"].items():
        if not row["available"]:
            continue
        by_index: dict[int, list[float]] = {}
        for rec in row["per_frame"]:
            value = rec.get("metrics", {}).get(metric)
            if value is not None and np.isfinite(value):
                by_index.setdefault(rec["index"], []).append(value)
        curves[name] = [(i + 1, float(np.mean(v))) for i, v in sorted(by_index.items())]
    return curves


def write_sequence_page(groups: dict, strips: dict, out_dir: Path, resamples: int, seed: int) -> str:
    """Write sequence.md with its figures; returns the page's text. Without a group (no sequence, or
    ``eval.sequence_methods`` empty) '', and a sequence.md an earlier eval left in ``out_dir`` is removed: the
    report folder describes this run."""
    if not groups:
        (out_dir / "sequence.md").unlink(missing_ok=True)
        return ""
    lines = ["# Sequences: every scene along its camera move", "",
             "Frame 1 apart from frames 2.. (frame 1 has no frame before it; a temporal method reads only the "
             "frames after there). Δ: paired over scenes "
             "(each scene's mean over its frames 2..), bootstrap 95 % interval, * when it excludes 0; needs "
             f"{MIN_FRAMES} scenes for an interval. "
             "Instability: mean |output's frame-to-frame change − the reference's| on x/(1+x), "
             "over pixels valid in both frames (`pipeline.temporal`); lower is steadier. FovVideoVDP: each sequence "
             "watched as a video, mean over scenes.", ""]
    for group, g in groups.items():
        if "skipped" in g:
            lines += [f"## {group}: no sequences ({g['skipped']})", ""]
            continue
        n = {len(v) for v in g["scenes"].values()}
        how = describe_averaging(g.get("window", 1), g.get("ahead", 0), g.get("gate")) or "input not averaged"
        lines += [f"## {group}: {len(g['scenes'])} sequences of {'/'.join(map(str, sorted(n)))} frames "
                  f"(temporal methods: {how}, filter weight {g['weight']:g}"
                  f"{', on both sides' if g.get('ahead') else ''})", ""]
        for spp, entry in g["spp"].items():
            lines += [f"### {spp} spp", "", *sequence_table(entry, resamples, seed), ""]
            for metric, label in (("psnr", "PSNR dB"), ("instability", "instability")):
                name = f"sequence_{group}_{metric}_spp{spp}.png"
                plot_curves(out_dir / name, per_frame_curves(entry, metric), f"{group}, {spp} spp: {label} per frame",
                            xlabel="frame", ylabel=label, log=False)
                lines.append(f"![{label} per frame]({name})")
            strip = strips.get(group, {}).get(spp)
            if strip:
                name = f"sequence_{group}_spp{spp}.gif"
                write_strip(strip, out_dir / name)
                lines += ["", f"![{strip['scene']} at {spp} spp, frame by frame]({name})"]
            lines.append("")
    text = "\n".join(lines) + "\n"
    write_text(out_dir / "sequence.md", text)
    return text


def write_strip(strip: dict, path: Path) -> None:
    """The strip of one scene: noisy / OIDN / its temporal filter / ours / ours_filter / ours_temporal / reference."""
    columns = [m for m in STRIP if m in strip["outputs"]]
    frames = [[strip["outputs"][m][t] for m in columns] + [f.reference] for t, f in enumerate(strip["frames"])]
    animated_strip(columns + ["reference"], frames, path)
