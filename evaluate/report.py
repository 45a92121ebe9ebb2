"""Tables (Markdown, CSV, JSON), the error-vs-time plot and the crop grids of ``make eval``.

Files under the report folder (``reports/<run>/`` by default):

- ``eval.md``: everything a reader needs — per group and spp a Table-1-like table (methods ×
  metrics, best in bold, ↑/↓ for the better direction, denoise seconds per frame), the error
  vs time table with the MC spp each method is worth, the MC convergence table, the stability
  summary and the run's provenance (config, git commit, package versions, machine).
- ``eval_<group>_spp<N>.csv``: one row per method (and per equal-time MC row).
- ``eval.json``: all of it including every per-frame number (inf written as the string "inf").
- ``error_vs_time_<group>.png``: MC convergence per frame and mean, methods as points, ours
  (ours_sN, ours_paper_skipN, ...) as curves over step counts (paper Fig. 4 analogue), equal-time MC as hollow marks.
- ``crops_<group>_spp<N>.png``: noisy / OIDN / Isik / ours / reference crops (gamma tonemap).
"""
from __future__ import annotations

import csv
import datetime
import io
import json
import math
import os
import subprocess
from pathlib import Path

import numpy as np

from mcdenoise.pipeline import figures
from mcdenoise.pipeline.config import Config, to_dict
from mcdenoise.pipeline.exr import atomic_write_bytes
from mcdenoise.pipeline.versions import machine, package_versions

from .compare import REFERENCES, frame_values, scored_rows
from .headline import headline
from .scoring import METRICS, best
from .stats import significant

EXTRA_PACKAGES = ("pyoidn", "flip-evaluator", "pyfvvdp", "safetensors", "matplotlib", "scipy")


# ---- provenance ------------------------------------------------------------------------------


def git_commit() -> dict:
    root = Path(__file__).resolve().parents[1]
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                             timeout=10).stdout.strip()
        # A read: git status would otherwise refresh the index under .git/index.lock, which a kill or a
        # full disk (the git process dies of SIGXFSZ) leaves behind, and the checkout's git stops working.
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=10,
                               env={**os.environ, "GIT_OPTIONAL_LOCKS": "0"}).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return {"commit": "unknown", "dirty": None}
    return {"commit": sha or "unknown", "dirty": bool(dirty) if sha else None}


def run_meta(cfg: Config, spps: list[int]) -> dict:
    return {"date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"), "spp": spps,
            "store": str(cfg.store), "runs": str(cfg.runs), "git": git_commit(),
            "packages": package_versions(EXTRA_PACKAGES), "machine": machine(), "config": to_dict(cfg)}


# ---- JSON ------------------------------------------------------------------------------------


def jsonable(x):
    """Plain JSON: non-finite floats as the strings "inf", "-inf", "nan"; tuples as lists."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return x if math.isfinite(x) else ("nan" if math.isnan(x) else ("inf" if x > 0 else "-inf"))
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def write_text(path: Path, text: str) -> None:
    """``text`` into ``path`` through a temporary file: a killed or failed eval leaves whole files only."""
    atomic_write_bytes(path, lambda tmp: Path(tmp).write_text(text))


def write_json(path: Path, data) -> None:
    write_text(path, json.dumps(jsonable(data), indent=1, allow_nan=False) + "\n")


def load_stability(out_dir: Path) -> dict | None:
    path = Path(out_dir) / "stability.json"
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


# ---- formatting ------------------------------------------------------------------------------

_DIGITS = {"l1": 4, "psnr": 2, "ssim": 4, "flip": 4, "hdr_flip": 4, "fvvdp": 3}


def fmt(key: str, v) -> str:
    if v is None:
        return "–"
    if isinstance(v, str):
        return v
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if math.isnan(v):
        return "nan"
    return f"{v:.{_DIGITS.get(key, 4)}f}"


def fmt_half(key: str, ci: dict | None) -> str:
    """" ± half-width" of a 95 % interval, or nothing when it has none (one frame, inf)."""
    if not ci or ci.get("lo") is None:
        return ""
    return f" ± {fmt(key, (ci['hi'] - ci['lo']) / 2)}"


def fmt_signed(key: str, v) -> str:
    return fmt(key, v) if v is None or not math.isfinite(v) else f"{v:+.{_DIGITS.get(key, 4)}f}"


def fmt_diff(key: str, d: dict | None, unit: str = "frames") -> str:
    """"+0.52 [+0.21, +0.83]*": mean difference, bootstrap interval, * when it excludes 0; without an interval,
    how many ``unit`` (what was resampled) there were."""
    if not d or d.get("diff") is None:
        return "–"
    if d.get("lo") is None:
        return f"{fmt_signed(key, d['diff'])} (no interval: {d['n']} {unit})"
    return (f"{fmt_signed(key, d['diff'])} [{fmt_signed(key, d['lo'])}, {fmt_signed(key, d['hi'])}]"
            f"{'*' if significant(d) else ''}")


def fmt_seconds(s) -> str:
    if s is None:
        return "–"
    return f"{s:.3g}"


def fmt_equivalent(value) -> str:
    spp, how = value
    if spp is None:
        return f"– ({how})"
    text = f"{spp:.3g}" if spp < 1e4 else f"{spp:.2e}"
    return text if how == "interpolated" else f"≈{text} ({how})"


def markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """A Markdown table; a '|' inside a cell (an error message, |n|) is escaped."""
    def line(cells):
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"
    return [line(header), "| " + " | ".join("---" for _ in header) + " |"] + [line(r) for r in rows]


def method_table(entry: dict, metric_names: list[str]) -> list[str]:
    """Paper Table 1 layout: one row per method and equal-time MC row, best value of a column bold."""
    rows = {n: r for n, r in entry["methods"].items()}
    values = {m: {n: r["metrics"][m] for n, r in rows.items() if r["available"] and r.get("metrics")}
              for m in metric_names}
    for n, et in entry["equal_time"].items():
        for m in metric_names:
            values[m][f"mc_equal_{n}"] = et["metrics"].get(m)
    winners = {m: best(values[m], m) for m in metric_names}
    cis = {n: r.get("ci", {}) for n, r in scored_rows(entry).items()}
    header = (["method"] + [f"{METRICS[m].column} {METRICS[m].arrow}" for m in metric_names]
              + ["s/frame", "device", "weights", "notes"])
    def cells(row: str) -> list[str]:
        return [(f"**{fmt(m, values[m].get(row))}**" if row in winners[m] else fmt(m, values[m].get(row)))
                + fmt_half(m, cis.get(row, {}).get(m)) for m in metric_names]

    lines = []
    for n, r in rows.items():
        if not r["available"]:
            lines.append([f"{r['label']} (`{n}`)"] + ["–"] * len(metric_names)
                         + ["–", "–", "–", f"not available: {r['reason']}"])
            continue
        notes = []
        if r.get("failed_frames"):
            bad = sorted({p["status"] for p in r["per_frame"] if p["status"] != "ok"})
            notes.append(f"{r['failed_frames']} frame(s) failed: {'; '.join(bad)[:200]}")
        if r.get("input_repaired"):
            notes.append(f"{r['input_repaired']} NaN/Inf input values repaired")
        lines.append([f"{r['label']} (`{n}`)"] + cells(n) + [fmt_seconds(r["seconds"]["median"]), r["device"],
                                                            r.get("checkpoint") or "–", "; ".join(notes)])
    for n, et in entry["equal_time"].items():
        notes = [f"{et['mode']}: {et['spp']:.1f} spp for {et['wanted_spp']:.1f} wanted (means over frames)"]
        measured = [p["measured_seconds"] for p in et["per_frame"] if p.get("measured_seconds") is not None]
        if measured:
            notes.append(f"measured render {fmt_seconds(float(np.mean(measured)))} s (first render in a worker "
                         "includes the JIT compile)")
        if et["capped_frames"]:
            notes.append(f"CAPPED on {et['capped_frames']} frame(s)")
        if et["failed_frames"]:
            notes.append(f"render failed on {et['failed_frames']} frame(s)")
        secs = float(np.mean([p["model_seconds"] for p in et["per_frame"]]))
        lines.append([f"MC at equal time to `{n}` (≈{et['spp']:.0f} spp)"] + cells(f"mc_equal_{n}") +
                     [f"{fmt_seconds(secs)} (render)", "renderer", "–", "; ".join(notes)])
    return markdown_table(header, lines)


def diff_table(entry: dict, metric_names: list[str], ref: str) -> list[str]:
    """Per row: mean over frames of (row − ``ref``) with its paired bootstrap 95 % interval."""
    rows = [[f"`{n}`"] + [fmt_diff(m, r["vs"][ref].get(m)) for m in metric_names]
            for n, r in scored_rows(entry).items() if ref in r.get("vs", {})]
    if not rows:
        return []
    return markdown_table(["method"] + [f"{METRICS[m].column} {METRICS[m].arrow}" for m in metric_names], rows)


def time_table(points: list[dict]) -> list[str]:
    rows = [[f"`{p['method']}`", fmt_seconds(p["seconds"]), fmt("l1", p["l1"]), fmt("psnr", p["psnr"]),
             fmt_equivalent(p["spp_equivalent_l1"]) if "spp_equivalent_l1" in p else "–",
             fmt_equivalent(p["spp_equivalent_psnr"]) if "spp_equivalent_psnr" in p else "–"] for p in points]
    return markdown_table(["method", "render + denoise s", "L1 ↓", "PSNR dB ↑", "MC spp with the same L1",
                   "MC spp with the same PSNR"], rows)


def mc_table(mean: list[dict]) -> list[str]:
    rows = [[str(p["spp"]), fmt_seconds(p["seconds"]), fmt("l1", p["l1"]), fmt("psnr", p["psnr"])] for p in mean]
    return markdown_table(["spp", "render s (model)", "L1 ↓", "PSNR dB ↑"], rows)


def reference_warning(mean: list[dict], min_db_per_doubling: float = 1.0) -> list[str]:
    """A warning when plain MC stops converging towards the reference: unbiased MC against an exact
    reference gains 3.01 dB of PSNR per doubling of the samples; much less on the last segment of
    the curve means the reference itself is off (noisy or biased), and every comparison with it."""
    pts = [p for p in mean if math.isfinite(p["psnr"])]
    if len(pts) < 2:
        return []
    a, b = pts[-2], pts[-1]
    gain = (b["psnr"] - a["psnr"]) / math.log2(b["spp"] / a["spp"])
    if gain >= min_db_per_doubling:
        return []
    return [f"**Warning:** plain MC gains only {gain:.2f} dB per doubling of samples between {a['spp']} and "
            f"{b['spp']} spp (3.01 dB for an exact reference): the reference is noisy or biased at this level, "
            "which caps every method's score and inflates the MC spp equivalents (check `make clean-report`).", ""]


def stability_summary(stab: dict | None) -> list[str]:
    if not stab:
        return ["Stability: not run yet (`make stability`)."]
    runs = [(c, m, cell) for c, row in stab["results"].items() for m, cell in row.items()]
    ran = [r for r in runs if r[2]["status"] != "not available"]
    bad = [r for r in ran if r[2]["status"] != "ok"]
    lines = [f"Stability ({stab.get('date', '?')}, stability.md): {len(ran) - len(bad)} of {len(ran)} method × case "
             f"runs gave finite outputs of the right shape."]
    lines += [f"- `{m}` on {c}: {cell['status']}" for c, m, cell in bad]
    return lines


def uncertainty_lines(entry: dict) -> list[str]:
    """The rows whose method gives its own per-pixel σ: how well σ ranks the actual error."""
    rows = [(n, r["uncertainty"]) for n, r in entry["methods"].items() if r.get("uncertainty")]
    if not rows:
        return []
    lines = ["Uncertainty (the standard deviation of the samples against the actual error per pixel; "
             "evaluate/uncertainty.py):", ""]
    def pct(u, key):
        v = u.get(key)
        return "–" if v is None or v != v else f"{100 * v:.1f} %"
    lines += markdown_table(["method", "Spearman ρ (mean over frames)", "error within 1σ (68.3 %)",
                             "within 2σ (95.4 %)", "frames"],
                            [[f"`{n}`", fmt("ssim", u["spearman_mean"]), pct(u, "within_1sigma"),
                              pct(u, "within_2sigma"), str(u["frames"])] for n, u in rows])
    if entry.get("uncertainty_plot"):
        lines += ["", f"Calibration plot: {entry['uncertainty_plot']}"]
    return lines + [""]


def _realizations_note(meta: dict) -> str:
    n = meta.get("config", {}).get("eval", {}).get("realizations", 1)
    return (f" Each frame's metrics are the mean over up to {n} noise realizations (disjoint groups of its stacks; "
            "eval.realizations), its crops the first." if n > 1 else "")


def format_markdown(result: dict) -> str:
    meta = result["meta"]
    names = result["metrics"]
    lines = ["# Evaluation", "", headline(result), "",
             f"Store `{meta['store']}`, runs `{meta['runs']}`, commit {meta['git']['commit'][:12]}"
             f"{' (uncommitted changes)' if meta['git'].get('dirty') else ''}, {meta['date']}, "
             f"{meta.get('seconds', 0):.1f} s. Metrics against the reference image; means over frames "
             "± half-width of the 95 % Student-t interval of the mean. "
             "Bold: best mean of the column. s/frame: median denoise wall time on this machine. Per-frame "
             "numbers: eval_frames.csv; per scene: per_scene_<group>_spp<N>.png." + _realizations_note(meta), ""]
    for what, why in result.get("metrics_missing", {}).items():
        lines.append(f"- Not in the tables: {what}: {why}.")
    lines.append("")
    for group, g in result["groups"].items():
        refs = sorted(set(g["reference"].values()))
        lines += [f"## {group}: {len(g['frames'])} frame(s), reference {', '.join(refs)}", ""]
        for spp, entry in g["spp"].items():
            lines += [f"### {group}, {spp} spp", ""]
            if "skipped" in entry:
                lines += [f"Skipped: {entry['skipped']}.", ""]
                continue
            lines += method_table(entry, names) + [""]
            for ref in REFERENCES:
                table = diff_table(entry, names, ref)
                if table:
                    lines += [f"Difference to `{ref}` ({group}, {spp} spp): mean over frames of method − {ref}, "
                              "paired bootstrap 95 % interval; * = the interval excludes 0 (a real difference):",
                              ""] + table + [""]
            lines += [f"Error against run time ({group}, {spp} spp; render seconds from the store's render-time "
                      "model, denoise seconds measured here; MC spp by log-log interpolation on the MC curve "
                      "below, extrapolation marked):", ""]
            lines += time_table(entry["time_vs_error"]) + [""]
            if entry.get("crops"):
                lines += [f"Crops: {entry['crops']}", ""]
            lines += uncertainty_lines(entry)
            if entry.get("per_scene"):
                lines += [f"Per scene (one dot per frame): {entry['per_scene']}", ""]
        lines += [f"Plain MC convergence ({group}, mean over frames; GT2 is the independent high-spp render):", ""]
        lines += mc_table(g["mc_mean"]) + [""] + reference_warning(g["mc_mean"])
        lines += [f"Plot: error_vs_time_{group}.png", ""]
    lines += stability_summary(result.get("stability")) + [""]
    m = meta["machine"]
    lines += ["## Provenance", "",
              f"- machine: {m.get('host')} — {m.get('platform')}, {m.get('cpus')} CPUs, torch threads "
              f"{m.get('torch_threads')}, CUDA {m.get('cuda')}",
              "- packages: " + ", ".join(f"{k} {v}" for k, v in meta["packages"].items()),
              "- config: in eval.json (`meta.config`)", ""]
    return "\n".join(lines)


def interval_columns(names: list[str]) -> list[str]:
    """CSV columns after the means: the t interval of each mean, then each paired difference."""
    cols = [f"{m}_ci_{end}" for m in names for end in ("lo", "hi")]
    return cols + [f"{m}_vs_{ref}{end}" for ref in REFERENCES for m in names for end in ("", "_lo", "_hi")]


def interval_cells(row: dict, names: list[str]) -> list:
    cells = [row.get("ci", {}).get(m, {}).get(end) for m in names for end in ("lo", "hi")]
    vs = row.get("vs", {})
    cells += [vs.get(ref, {}).get(m, {}).get(end) for ref in REFERENCES for m in names for end in ("diff", "lo", "hi")]
    return ["" if v is None else v for v in cells]


def write_csv(path: Path, entry: dict, names: list[str]) -> None:
    f = io.StringIO(newline="")
    w = csv.writer(f)
    w.writerow(["method", "label", "available", "reason", *names, "seconds_median", "seconds_mean",
                "failed_frames", "input_repaired", "device", *interval_columns(names)])
    for n, r in entry["methods"].items():
        if not r["available"]:
            w.writerow([n, r["label"], False, r["reason"], *[""] * len(names), "", "", "", "", "",
                        *[""] * len(interval_columns(names))])
            continue
        w.writerow([n, r["label"], True, "", *[fmt(m, r["metrics"][m]) for m in names], r["seconds"]["median"],
                    r["seconds"]["mean"], r["failed_frames"], r["input_repaired"], r["device"],
                    *interval_cells(r, names)])
    for n, et in entry["equal_time"].items():
        w.writerow([f"mc_equal_{n}", et["label"], True, f"{et['mode']}, {et['spp']:.0f} spp",
                    *[fmt(m, et["metrics"][m]) for m in names], "", "", et["failed_frames"], 0, "renderer",
                    *interval_cells(et, names)])
    write_text(path, f.getvalue())


def write_frames_csv(path: Path, result: dict) -> None:
    """Every scored row × frame × metric: group, spp, method, frame, status, seconds, one column per metric."""
    names = result["metrics"]
    f = io.StringIO(newline="")
    w = csv.writer(f)
    w.writerow(["group", "spp", "method", "frame", "status", "denoise_seconds", "mc_spp", *names])
    for group, g in result["groups"].items():
        for spp, entry in g["spp"].items():
            if "skipped" in entry:
                continue
            for n, r in scored_rows(entry).items():
                for p in r["per_frame"]:
                    m = p.get("metrics", {})
                    w.writerow([group, spp, n, p["frame"], p.get("status", p.get("error", "ok")),
                                p.get("seconds", ""), p.get("spp", ""), *[m.get(k, "") for k in names]])
    write_text(path, f.getvalue())


def write_eval(result: dict, out_dir: Path) -> str:
    out_dir = Path(out_dir)
    for group, g in result["groups"].items():
        for spp, entry in g["spp"].items():
            if "skipped" not in entry:
                write_csv(out_dir / f"eval_{group}_spp{spp}.csv", entry, result["metrics"])
        plot_error_vs_time(g, out_dir / f"error_vs_time_{group}.png", group)
    write_frames_csv(out_dir / "eval_frames.csv", result)
    write_json(out_dir / "eval.json", result)
    text = format_markdown(result)
    if result.get("sequences"):
        text += "\nSequences: every scene along its camera move, frame 1 apart: [sequence.md](sequence.md)\n"
    write_text(out_dir / "eval.md", text)
    return text


# ---- figures ---------------------------------------------------------------------------------


def crop_figure(crops: list[tuple[str, list]], titles: list[str], path: Path, size: int) -> None:
    figures.crop_grid(crops, titles, path, size=size)


def plot_error_vs_time(g: dict, path: Path, group: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spps = [s for s, e in g["spp"].items() if "skipped" not in e]
    fig, axes = plt.subplots(max(1, len(spps)), 2, figsize=(11, 3.6 * max(1, len(spps))), squeeze=False)
    for row, spp in enumerate(spps or [None]):
        for col, (key, name) in enumerate((("l1", "L1 (HDR, [0,6]) ↓"), ("psnr", "PSNR dB ↑"))):
            ax = axes[row][col]
            for frame, pts in g["mc_curve"].items():
                ax.plot([p["seconds"] for p in pts], [p[key] for p in pts], color="0.8", lw=0.8, zorder=1)
            mean = g["mc_mean"]
            ax.plot([p["seconds"] for p in mean], [p[key] for p in mean], "o-", color="0.3", lw=1.5, ms=3,
                    label="plain MC (mean; grey: per frame)", zorder=2)
            for p in mean:
                ax.annotate(f"{p['spp']}", (p["seconds"], p[key]), fontsize=6, color="0.3",
                            textcoords="offset points", xytext=(2, 3))
            if spp is not None:
                _plot_points(ax, g["spp"][spp]["time_vs_error"], key)
                ax.set_title(f"{group}, {spp} spp input: {name}", fontsize=9)
            ax.set_xscale("log")
            if key == "l1":
                ax.set_yscale("log")
            ax.set_xlabel("render + denoise seconds per frame")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6)
    fig.tight_layout()
    figures.save_figure(fig, path, dpi=110)


# Diffusion rows of one kind (evaluate.methods.curve_kind: ours, ours_paper, ...) are drawn as one curve over
# their step counts when there are several; every other row is a point.
def _curves(points: list[dict], key: str) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for p in points:
        if p["kind"].startswith(("ours", "base_only")) and p[key] is not None and math.isfinite(p[key]):
            out.setdefault(p["kind"], []).append(p)
    return {k: sorted(v, key=lambda p: p["seconds"]) for k, v in out.items() if len(v) > 1}


def _plot_points(ax, points: list[dict], key: str) -> None:
    curves = _curves(points, key)
    for i, (kind, curve) in enumerate(curves.items()):
        ax.plot([p["seconds"] for p in curve], [p[key] for p in curve], "s-", color=f"C{(i + 3) % 10}",
                label=f"{kind} over step counts", zorder=4)
    for i, p in enumerate(points):
        v = p[key]
        if v is None or not math.isfinite(v) or p["kind"] in curves:
            continue
        hollow = p["kind"] == "mc_equal_time"
        ax.scatter([p["seconds"]], [v], marker="D" if hollow else "o", s=28, zorder=3,
                   facecolors="none" if hollow else f"C{i % 10}", edgecolors=f"C{i % 10}", label=p["method"])


def per_scene_figure(entry: dict, metric_names: list[str], path: Path, title: str) -> str | None:
    """One panel per metric: scenes along x, the methods side by side within a scene, one dot per
    frame (the spread a mean hides: is a lead one scene or all of them?). Returns the file name."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = {n: r for n, r in entry["methods"].items() if r["available"]}
    scenes = sorted({f.split("/")[0] for r in rows.values() for f in frame_values(r, metric_names[0])}) \
        if rows and metric_names else []
    if not scenes:
        return None
    width = 0.8 / len(rows)
    fig, axes = plt.subplots(len(metric_names), 1, figsize=(2 + (0.6 + 0.15 * len(rows)) * len(scenes),
                                                           2.3 * len(metric_names)), squeeze=False)
    for ax, m in zip(axes[:, 0], metric_names):
        for i, (name, row) in enumerate(rows.items()):
            pts = [(scenes.index(f.split("/")[0]), v) for f, v in frame_values(row, m).items() if math.isfinite(v)]
            ax.scatter([x - 0.4 + width * (i + 0.5) for x, _ in pts], [v for _, v in pts], s=12, color=f"C{i % 10}",
                       label=name, zorder=3)
        for x in range(1, len(scenes)):
            ax.axvline(x - 0.5, color="0.85", lw=0.8)
        ax.set_xticks(range(len(scenes)), scenes, fontsize=7, rotation=20)
        ax.set_ylabel(f"{METRICS[m].column} {METRICS[m].arrow}", fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    axes[0, 0].set_title(f"{title}: one dot per frame", fontsize=9)
    axes[0, 0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    figures.save_figure(fig, path, dpi=100, bbox_inches="tight")
    return path.name
