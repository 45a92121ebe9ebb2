"""``python -m pipeline plan --config FILE``: what a config costs before anything runs.

A cost model of the dataset stage from the config alone, with constants measured on a real
machine by ``python -m pipeline plan --measure`` (kept below with the date and the machine):

- **render time** of one image = ``overhead + samples / rate``, in CPU-core-seconds. ``rate`` is
  the renderer's samples per second per core (``render.buffers.render_image``: the split
  integrator with every feature and the per-pixel moments), fitted per resolution from a low
  and a high sample count (so the fixed cost per image, which dominates 4 spp stacks, is not
  taken for sampling). The cost per sample grows with ``render.max_depth``: measured at two
  depths and interpolated linearly (extrapolated, floored at a quarter of the shallow cost,
  outside them). Other resolutions use the nearest measured one, scaling the overhead by the
  pixel count.
- **scene kinds**: the constants are measured on scenes of objects on a ground. A furnished interior or a
  product shot costs more per sample (more geometry, light that arrives after more bounces, glass):
  ``kind_cost`` holds each kind's cost per sample over an objects scene's (``measure_kinds``), and a
  config's random scenes cost the mean over its kind probabilities (``scene.interior_probability``,
  ``scene.product_probability``); the stress presets count as objects scenes.
- **writing** an image (EXR ZIP, atomic rename, SHA-256) costs ``write_s_per_mpx`` per
  megapixel; building the scene once per frame ``build_s``.
- **ground-truth spp**: ``dataset.gt_spp`` without a target. With ``dataset.gt_target_psnr`` (a
  progressive GT, ``render.progressive``) the expected spp of a GT is the mean, over the measured
  distribution of a GT's estimated PSNR at a reference spp (``gt_psnr``: the 20 mid-quantiles,
  2.5 % ... 97.5 %, of the GTs of the default dataset at 1024 spp), of the spp the stop rule reaches
  from it (``render.progressive.expected_spp``: +3 dB per doubling, whole passes, the cap); each pass
  costs the per-image overhead.
- **disk** per image from the channel schema (``pipeline.schema``: float32 radiance and
  variances, half features), times the ZIP ratio measured on real frames (ground truths
  compress better than 4 spp stacks); ``gt_clean`` is one float32 RGB image.

``--store STORE`` replaces the measured rate by one fitted to the frames of an existing store
(their ``frame.json`` render seconds, spp and resolution; the store's ``render.threads`` and
``executor.workers`` tell how many cores one render used), its bytes per image and, where its
images record an estimated PSNR, the GT error distribution, so a plan for a
cluster can be calibrated on a pilot run there.

Wall time for N workers assumes perfect scaling over frames (frames are independent; measured
Ray 1→2 workers on this machine in docs/scaling.md).
"""
from __future__ import annotations

import json
import math
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.exr import StoreError

# Stored bytes of a frame over the exact encoding's, for compact images without a beauty view (format
# version 3), and the growth of a compact frame by format version 4's half-precision beauty view: the
# measurements are MEASURED's encoding_factor_source.
COMPACT_BYTES = 0.611
COMPACT_ZSTD_BYTES = 0.517
BEAUTY_VIEW_FACTOR = 1.102

# Measured by `python -m pipeline plan --measure` (see measure()). Re-measure on the target
# machine and paste the printed JSON here (keeping encoding_factor's formula: --measure does not
# measure it), or calibrate with --store.
MEASURED: dict = {
 "date": "2026-11-22",
 "machine": "AMD EPYC, 2 cores, 1 render thread(s), CPU time (load average 6.5)",
 "source": "measured",
 "render": {
  "128": {
   "5": {
    "rate": 1729362,
    "overhead_s": 0.0401
   },
   "8": {
    "rate": 1558756,
    "overhead_s": 0.037
   }
  },
  "256": {
   "5": {
    "rate": 1760346,
    "overhead_s": 0.0805
   },
   "8": {
    "rate": 1529299,
    "overhead_s": 0.1025
   }
  }
 },
 "build_s": 0.22,
 "write_s_per_mpx": 1.579,
 "zip_ratio": {
  "gt": 0.48,
  "stack": 0.453,
  "gt_clean": 0.879
 },
 "gt_spp_for_ratio": 1024,
 "encoding": "exact",
 "encoding_factor": {"exact": 1.0, "compact": round(COMPACT_BYTES * BEAUTY_VIEW_FACTOR, 3),
                     "compact-zstd": round(COMPACT_ZSTD_BYTES * BEAUTY_VIEW_FACTOR, 3)},
 "encoding_factor_source": "compact-zstd: verify data/default --bytes 100: 11.92 / 23.05 MiB per frame (86 frames), "
                           "2026-12-01; compact: verify data/encodings --encodings 4: 15.22 / 24.90 MiB per frame (4 frames "
                           "of configs/default.yaml), 2026-12-04; both x 1.102 for the half beauty view of format "
                           "version 4 (docs/store.md: 9.17 -> 10.11 MiB per frame of 22 frames, 2026-12-06)",
 "kind_cost": {"interior": 1.92, "product": 0.58,
               "source": "measure_kinds on configs/ship_rooms.yaml (3 scenes per kind, 128x128, max_depth 8, CPU time of "
                         "1 thread beside a render), 2026-12-06; data/ship_rooms's first 55 frames agree: 1566 against "
                         "809 ns per sample for interiors and objects scenes (1.94)"},
 "gt_psnr": {
  "source": "data/default (configs/default.yaml, 86 frames, 172 GTs at 1024 spp, 128x128, max_depth 8), 2026-12-01",
  "spp": 1024,
  "quantiles": [38.0, 39.5, 41.3, 42.5, 43.5, 45.1, 46.9, 47.6, 48.2, 48.7, 49.7, 50.2, 50.6, 51.5, 52.9, 54.8,
                56.0, 56.9, 58.6, 85.1]
 }
}

GB = 1e9
DEFAULT_WORKERS = (1, 2, 16, 64, 256, 1024)


# ---- bytes -------------------------------------------------------------------------------------

def disk_ratio(c: dict, kind: str, encoding: str) -> float:
    """Stored bytes over raw bytes of a ``kind`` image ('gt' or 'stack') written with ``encoding``.

    ``zip_ratio`` was measured with the constants' own ``encoding`` (the exact one when not
    recorded); for another encoding it is scaled by ``encoding_factor``, each encoding's bytes over
    the exact encoding's for the same images (docs/store.md, "Encodings")."""
    factor = c["encoding_factor"]
    return c["zip_ratio"][kind] * factor[encoding] / factor[c.get("encoding", "exact")]


def raw_bytes_per_pixel(omit: tuple[str, ...] = ()) -> int:
    """Uncompressed bytes per pixel of a complete image: every buffer and its variance."""
    total = 0
    for b in schema.BUFFERS:
        if b.name in omit:
            continue
        total += b.size * np.dtype(b.dtype).itemsize + b.size * 4
    return total


# ---- the model ---------------------------------------------------------------------------------

def _nearest(table: dict, res: int) -> dict:
    key = min(table, key=lambda r: abs(math.log(int(r) / res)))
    return table[key], int(key)


def seconds_per_sample(constants: dict, resolution: int, max_depth: int) -> tuple[float, float]:
    """(core-seconds per sample, core-seconds of fixed cost per image) at this side and depth."""
    per_res, res = _nearest(constants["render"], resolution)
    depths = sorted(per_res, key=int)
    lo, hi = per_res[depths[0]], per_res[depths[-1]]
    d0, d1 = int(depths[0]), int(depths[-1])
    c0, c1 = 1.0 / lo["rate"], 1.0 / hi["rate"]
    cost = c0 if d1 == d0 else c0 + (c1 - c0) * (max_depth - d0) / (d1 - d0)
    cost = max(cost, 0.25 * c0)
    overhead = float(np.mean([v["overhead_s"] for v in per_res.values()])) * (resolution / res) ** 2
    return cost, max(overhead, 0.0)


def expected_gt_spp(d, constants: dict) -> tuple[float, float]:
    """(expected spp, expected passes) of one ground truth (see the module docstring)."""
    from .progressive import StopRule, expected_spp

    if d.gt_target_psnr is None:
        return d.gt_spp, 1
    rule = StopRule(d.gt_target_psnr, d.gt_pass_spp, d.gt_max_spp)
    dist = constants["gt_psnr"]
    spps = [expected_spp(q, dist["spp"], rule) for q in dist["quantiles"]]
    return float(np.mean(spps)), float(np.mean(spps)) / d.gt_pass_spp


def estimate(cfg: Config, constants: dict | None = None) -> dict:
    """Per-frame and total cost of the config's dataset stage (see the module docstring)."""
    from .stress import STRESS_PRESETS

    c = constants or MEASURED
    d = cfg.dataset
    w, h = (int(v) for v in d.resolution)
    px = w * h
    side = math.sqrt(px)
    stress = (len(STRESS_PRESETS) if d.stress in ("all", ["all"]) else len(d.stress)) * d.stress_copies
    frames = (d.scenes + stress) * d.frames
    cost, overhead = seconds_per_sample(c, side, cfg.render.max_depth)
    # the constants are objects scenes'; interiors and product shots cost more per sample (kind_cost), the
    # stress presets are counted as objects scenes
    factor = kind_factor(cfg.scene, c)
    cost *= (d.scenes * factor + stress) / max(d.scenes + stress, 1)
    write = c["write_s_per_mpx"] * px / 1e6
    raw = raw_bytes_per_pixel() * px
    gt_spp, gt_passes = expected_gt_spp(d, c)
    parts = {
        "gt": {"images": 2, "spp": gt_spp, "passes": gt_passes, "target_psnr": d.gt_target_psnr,
               "core_s": 2 * (gt_passes * overhead + px * gt_spp * cost + write),
               "bytes": 2 * raw * disk_ratio(c, "gt", cfg.render.encoding)},
        "stacks": {"images": d.stacks, "spp": d.stack_spp,
                   "core_s": d.stacks * (overhead + px * d.stack_spp * cost + write),
                   "bytes": d.stacks * raw * disk_ratio(c, "stack", cfg.render.encoding)},
        "gt_clean": {"images": 1, "spp": None, "core_s": None,
                     "bytes": px * 3 * 4 * c["zip_ratio"]["gt_clean"]},
    }
    frame_core_s = parts["gt"]["core_s"] + parts["stacks"]["core_s"] + c["build_s"]
    frame_bytes = sum(p["bytes"] for p in parts.values())
    return {
        "frames": frames, "scenes": d.scenes, "stress_scenes": stress, "resolution": [w, h],
        "max_depth": cfg.render.max_depth, "samples_per_frame": px * (2 * gt_spp + d.stacks * d.stack_spp),
        "kind_factor": factor,
        "seconds_per_sample": cost, "overhead_s": overhead, "build_s": c["build_s"], "parts": parts,
        "frame_core_s": frame_core_s, "frame_bytes": frame_bytes,
        "total_core_h": frame_core_s * frames / 3600, "total_bytes": frame_bytes * frames,
        "source": c.get("source", "measured"), "measured": {k: c.get(k) for k in ("date", "machine")},
    }


def _duration(seconds: float) -> str:
    for unit, size in (("d", 86400), ("h", 3600), ("min", 60)):
        if seconds >= size:
            return f"{seconds / size:.1f} {unit}"
    return f"{seconds:.1f} s"


def format_table(est: dict, workers: tuple[int, ...] = DEFAULT_WORKERS, title: str = "") -> str:
    p, n = est["parts"], est["frames"]
    w, h = est["resolution"]
    lines = [
        f"plan{(' for ' + title) if title else ''}: {est['scenes']} scenes + {est['stress_scenes']} stress "
        f"= {n} frames at {w}x{h}, max_depth {est['max_depth']}, "
        f"{est['samples_per_frame'] / 1e6:.1f} M samples per frame"
        + (f"; the random scenes' kinds cost {est['kind_factor']:.2f}x objects scenes per sample (kind_cost)"
           if est["kind_factor"] != 1.0 else ""),
        f"  cost model: {est['seconds_per_sample'] * 1e9:.0f} core-ns per sample + {est['overhead_s'] * 1e3:.0f} ms "
        f"per image + {est['build_s']:.2f} s scene build per frame ({est['source']}; "
        f"{est['measured']['date']}, {est['measured']['machine']})",
        "",
        "| part | per frame: CPU | per frame: disk | total: CPU | total: disk |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]

    def row(name, core_s, nbytes):
        cpu = f"{core_s:,.1f} core-s" if core_s is not None else "not modelled"
        tot = f"{core_s * n / 3600:,.1f} core-h" if core_s is not None else "-"
        lines.append(f"| {name} | {cpu} | {nbytes / 2**20:,.1f} MiB | {tot} | {nbytes * n / GB:,.2f} GB |")

    g = p["gt"]
    gt_label = (f"GT ({g['images']} x {g['spp']} spp)" if g["target_psnr"] is None else
                f"GT ({g['images']} x ~{g['spp']:.0f} spp expected: target {g['target_psnr']:g} dB, "
                f"~{g['passes']:.1f} passes)")
    row(gt_label, g["core_s"], g["bytes"])
    row(f"stacks ({p['stacks']['images']} x {p['stacks']['spp']} spp)", p["stacks"]["core_s"], p["stacks"]["bytes"])
    row("scene build", est["build_s"], 0)
    row("gt_clean (1 image)", None, p["gt_clean"]["bytes"])
    row("**all**", est["frame_core_s"], est["frame_bytes"])
    lines += ["", "Disk per frame in MiB (2^20 B), totals in GB (10^9 B). gt_clean's compute (the cleaner's "
              "training and inference) is not modelled: see docs/scaling.md.",
              "", "| CPU cores | wall time (perfect scaling over frames) |", "| ---: | ---: |"]
    for k in workers:
        lines.append(f"| {k} | {_duration(est['frame_core_s'] * n / k)} |")
    return "\n".join(lines)


# ---- measuring and calibrating ------------------------------------------------------------------

def _fit(points: list[tuple[float, float]]) -> tuple[float, float]:
    """Least squares t = a + b·samples over (samples, seconds): (a, b), a >= 0, b > 0."""
    x = np.array([p[0] for p in points], float)
    y = np.array([p[1] for p in points], float)
    if len(set(x.tolist())) < 2:
        b = float(np.sum(y) / np.sum(x))
        return 0.0, b
    b, a = np.polyfit(x, y, 1)
    # Timing noise (a loaded machine, tiny renders) can give a negative intercept or even a
    # non-positive slope: fall back to a line through the origin, whose slope is always > 0.
    if a < 0 or b <= 0:
        a, b = 0.0, float(np.sum(x * y) / np.sum(x * x))
    return float(a), float(b)


def _cpu_seconds(fn) -> float:
    """CPU time of this process (all threads) spent in ``fn``: core-seconds, whatever else the
    machine runs at the same time (wall time on a shared machine would count the waiting)."""
    t0 = time.process_time()
    fn()
    return time.process_time() - t0


def measure(cfg: Config, resolutions=(128, 256), depths=(5, 8), spps=(4, 64), scenes: int = 2,
            threads: int = 1, gt_spp: int = 1024, repeats: int = 2) -> dict:
    """Measure the constants of the model on this machine (about two minutes on 2 cores)."""
    import drjit as dr

    from mcdenoise.pipeline.mitsuba_env import import_mitsuba

    from .buffers import needed_features
    from .scene import build_scene, build_sensor, random_scene

    mi = import_mitsuba(cfg.render.variant, threads)
    used_threads = dr.thread_count()
    timings: dict = {}
    builds, writes, ratios = [], [], {"gt": [], "stack": [], "gt_clean": []}
    tmp = Path(tempfile.mkdtemp(prefix="plan-measure-"))
    try:
        for i in range(scenes):
            desc = random_scene(cfg.scene, cfg.seed, i, 1)
            t0 = time.process_time()
            scene = build_scene(mi, desc)
            features = needed_features(mi, scene)
            builds.append(time.process_time() - t0)
            for res in resolutions:
                sensor = build_sensor(mi, desc, 0, res, res)
                _time_renders(mi, scene, sensor, features, cfg, res, depths, spps, repeats, timings)
                _measure_writes(mi, scene, sensor, features, cfg, i, res, resolutions, depths, gt_spp, tmp,
                                writes, ratios)
            del scene
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    render = _fit_render(timings)
    return {
        "date": time.strftime("%Y-%m-%d"),
        "machine": f"{_cpu_name()}, {os.cpu_count()} cores, {used_threads} render thread(s), "
                   f"CPU time (load average {os.getloadavg()[0]:.1f})",
        "source": "measured",
        "render": render,
        "build_s": round(float(np.mean(builds)), 3),
        "write_s_per_mpx": round(float(np.mean(writes)), 3),
        "zip_ratio": {k: round(float(np.mean(v)), 3) for k, v in ratios.items()},
        "gt_spp_for_ratio": gt_spp,
        "encoding": cfg.render.encoding,
        "encoding_factor": MEASURED["encoding_factor"],
    }


SCENE_KINDS = ("objects", "interior", "product")


def measure_kinds(cfg: Config, scenes: int = 3, res: int = 128, spps=(8, 32), threads: int = 1) -> dict:
    """Core-seconds per sample of each scene kind over that of ``objects`` scenes (the kind the render constants
    were measured on): ``scenes`` scenes of each kind, drawn by the config's generators, at ``res``² and the
    config's ``render.max_depth``, the per-sample cost fitted from two sample counts as the constants are."""
    import dataclasses

    from mcdenoise.pipeline.mitsuba_env import import_mitsuba

    from .buffers import needed_features
    from .scene import build_scene, build_sensor, random_scene

    mi = import_mitsuba(cfg.render.variant, threads)
    only = {"objects": (0.0, 0.0), "interior": (1.0, 0.0), "product": (0.0, 1.0)}
    cost = {}
    for kind in SCENE_KINDS:
        scene_cfg = dataclasses.replace(cfg.scene, interior_probability=only[kind][0], product_probability=only[kind][1])
        timings: dict = {}
        for i in range(scenes):
            desc = random_scene(scene_cfg, cfg.seed, i, 1)
            scene = build_scene(mi, desc)
            _time_renders(mi, scene, build_sensor(mi, desc, 0, res, res), needed_features(mi, scene), cfg, res,
                          (cfg.render.max_depth,), spps, 2, timings)
            del scene
        cost[kind] = _fit(timings[str(res)][str(cfg.render.max_depth)])[1]
    return {kind: round(cost[kind] / cost["objects"], 2) for kind in SCENE_KINDS if kind != "objects"}


def kind_factor(scene_cfg, c: dict) -> float:
    """The mean per-sample cost of the random scenes of ``scene_cfg`` over that of ``objects`` scenes: each kind's
    ``kind_cost`` weighted by its probability (``render.scene.scene_kind``)."""
    pi, pp = float(scene_cfg.interior_probability), float(scene_cfg.product_probability)
    if pi <= 0 and pp <= 0:
        return 1.0
    costs = c.get("kind_cost", {})
    pi = min(max(pi, 0.0), 1.0)
    rest = 1.0 - pi
    pp = rest * min(max(pp, 0.0), 1.0)
    return pi * costs.get("interior", 1.0) + pp * costs.get("product", 1.0) + (rest - pp)


def _time_renders(mi, scene, sensor, features, cfg: Config, res: int, depths, spps, repeats: int,
                  timings: dict) -> None:
    """Add (samples, best CPU seconds) of each depth and spp at resolution ``res`` to ``timings[res][depth]``."""
    from .buffers import render_image

    for depth in depths:
        kw = dict(features=features, max_depth=depth, rr_depth=cfg.render.rr_depth)
        render_image(mi, scene, sensor, spp=spps[0], seed=99, **kw)   # compile
        for spp in spps:
            best = min(_cpu_seconds(lambda: render_image(mi, scene, sensor, spp=spp, seed=r, **kw))
                       for r in range(repeats))
            timings.setdefault(str(res), {}).setdefault(str(depth), []).append((res * res * spp, best))


def _measure_writes(mi, scene, sensor, features, cfg: Config, i: int, res: int, resolutions, depths, gt_spp: int,
                    tmp: Path, writes: list, ratios: dict) -> None:
    """Add the write time per megapixel and the compression ratios of a stack and a ground truth at ``res``."""
    from mcdenoise.pipeline.exr import write_image
    from mcdenoise.pipeline.store import sha256

    from .buffers import render_image

    # bytes and write time of a stack and a ground truth at the largest depth
    raw = raw_bytes_per_pixel() * res * res
    for kind, spp in (("stack", cfg.dataset.stack_spp), ("gt", gt_spp)):
        if kind == "gt" and res != min(resolutions):
            continue   # the 1024 spp reference only at the small size (time)
        result = render_image(mi, scene, sensor, spp=spp, seed=7, features=features,
                              max_depth=max(depths), rr_depth=cfg.render.rr_depth)
        path = tmp / f"{kind}{i}_{res}.exr"
        t0 = time.process_time()
        write_image(path, result.buffers, result.constants, encoding=cfg.render.encoding)
        sha256(path)
        writes.append((time.process_time() - t0) / (res * res / 1e6))
        ratios[kind].append(path.stat().st_size / raw)
        if kind == "gt":
            clean = tmp / f"clean{i}.exr"
            color = result.buffers["color"]
            write_image(clean, {"color": color, "color.variance": np.zeros_like(color)})
            ratios["gt_clean"].append(clean.stat().st_size / (res * res * 12))


def _fit_render(timings: dict) -> dict:
    """The render constants of each resolution and depth: samples per second and overhead, fitted to ``timings``."""
    render = {}
    for res, per_depth in timings.items():
        for depth, points in per_depth.items():
            a, b = _fit(points)
            render.setdefault(res, {})[depth] = {"rate": round(1.0 / b), "overhead_s": round(a, 4)}
    return render


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def calibrate_from_store(root: str | Path, constants: dict | None = None, max_frames: int = 200) -> dict:
    """The model's constants with rate, overhead and bytes fitted to an existing store's frames (the rate of
    objects scenes: each frame's samples weighted by its scene kind's ``kind_cost``)."""
    from mcdenoise.pipeline.exr import store_encoding
    from mcdenoise.pipeline.store import Store

    c = json.loads(json.dumps(constants or MEASURED))
    store = Store(root)
    m = store.manifest()
    conf = m.get("config", {})
    threads = int(conf.get("render", {}).get("threads", 0) or 0)
    workers = int(conf.get("executor", {}).get("workers", 1) or 1)
    cpus = os.cpu_count() or 1
    cores = min(threads, cpus / workers) if threads > 0 else cpus / workers
    depth = int(conf.get("render", {}).get("max_depth", 8))
    points, gt_ratio, stack_ratio, sizes, gt_psnr, encodings = [], [], [], [], [], set()
    frames, kinds = 0, {}
    for key in store.frames():
        rec = store.frame_record(key.scene, key.frame)
        if rec is None:
            continue
        if key.scene not in kinds:      # per sample, a frame costs its kind's kind_cost times an objects frame
            scene = store.scene_manifest(key.scene)
            kind = "objects" if scene.get("preset") else (scene.get("description") or {}).get("kind", "objects")
            kinds[key.scene] = c.get("kind_cost", {}).get(kind, 1.0)
        px = int(rec["width"]) * int(rec["height"])
        sizes.append(math.sqrt(px))
        for name, img in rec["images"].items():
            if img.get("render_seconds") is None or img.get("reused"):
                continue
            if img.get("estimated_psnr") is not None:   # the GT's error at the reference spp (+3 dB per doubling)
                gt_psnr.append(float(img["estimated_psnr"]) + 10 * math.log10(c["gt_psnr"]["spp"] / int(img["spp"])))
            points.append((px * int(img["spp"]) * kinds[key.scene], float(img["render_seconds"]) * cores))
            (gt_ratio if name.startswith("gt") else stack_ratio).append(
                int(img["bytes"]) / (raw_bytes_per_pixel() * px))
            encodings.add(store_encoding(img))
        frames += 1
        if frames >= max_frames:
            break
    if not points:
        raise StoreError(f"{store.root}: no rendered frame with render times to calibrate from")
    a, b = _fit(points)
    side = int(round(float(np.median(sizes))))
    # Keep the measured depth dependence: scale every measured depth of the nearest size.
    base, res = _nearest(c["render"], side)
    measured_cost, _ = seconds_per_sample(c, side, depth)
    scale = b / measured_cost
    c["render"] = {str(side): {d: {"rate": v["rate"] / scale, "overhead_s": a} for d, v in base.items()}}
    if len(encodings) == 1:   # the ratios below are that encoding's (a mixed store keeps the constants' label)
        c["encoding"] = encodings.pop()
    if gt_ratio:
        c["zip_ratio"]["gt"] = float(np.mean(gt_ratio))
    if stack_ratio:
        c["zip_ratio"]["stack"] = float(np.mean(stack_ratio))
    if gt_psnr:
        c["gt_psnr"] = {"source": f"{len(gt_psnr)} GTs of {store.root}", "spp": c["gt_psnr"]["spp"],
                        "quantiles": np.percentile(gt_psnr, np.arange(2.5, 100, 5)).round(2).tolist()}
    c["source"] = (f"calibrated on {frames} frames of {store.root} ({cores:g} cores per render, "
                   f"max_depth {depth}; {1 / b / 1e6:.2f} M samples/core-s there)")
    return c


def run_plan(cfg: Config, title: str = "", store: str | None = None,
             workers: tuple[int, ...] = DEFAULT_WORKERS, as_json: bool = False) -> dict:
    constants = calibrate_from_store(store) if store else MEASURED
    est = estimate(cfg, constants)
    print(json.dumps(est, indent=1) if as_json else format_table(est, workers, title))
    return est
