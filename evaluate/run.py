"""``make eval`` → ``python -m pipeline eval``: every method on the test frames, per spp.

For each group of frames (the ``eval.split`` split against GT_clean; the store's ``stress``
split against GT_clean; the store's ``external`` split, e.g. scenes given with ``--scene``,
against GT_clean where it exists, else GT1 — the paper does not post-process its external test
scenes) and each spp of ``eval.spp``:

1. every method of ``eval.methods`` denoises the first stacks pooled to that spp, or each of
   ``eval.realizations`` disjoint groups of stacks, the frame's metrics their mean
   (``evaluate.harness``: inputs repaired and counted, denoise wall time measured, output
   checked); a method that cannot run is a row with its reason;
2. metrics against the reference (``evaluate.scoring``), means over frames with 95 % intervals,
   and paired bootstrap intervals of the differences to OIDN and the noisy input
   (``evaluate.compare``);
3. plain MC at equal time to each of ``eval.equal_time_methods`` (``evaluate.montecarlo``);
4. the MC convergence curve per frame and the spp plain MC needs to match each method
   (``evaluate.timing.spp_equivalent``), and a crop grid.

Tables, plots and the raw per-frame numbers go to ``reports/<run>/`` (``evaluate.report``).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from mcdenoise.pipeline.config import Config, ConfigError
from mcdenoise.pipeline.exr import StoreError
from mcdenoise.pipeline.progress import progress
from mcdenoise.pipeline.store import FrameKey, Store, poolable

from . import report, uncertainty
from .compare import annotate
from .harness import finite_output, run_method
from .methods import Loader, MethodUnavailable, check_names, curve_kind, label
from .montecarlo import equal_time_images, mc_curve, mean_curve
from .scoring import NOT_COMPUTED, check_metrics, score, usable_metrics
from .sequence import check_sequence_names, evaluate_sequences, sequences
from .sequence_report import write_sequence_page
from .timing import equal_time_spp, psnr_to_mse, render_cost, spp_equivalent

EXTERNAL = "external"
STRESS = "stress"
CROP_METHODS = ("noisy", "oidn", "oidn_prefilter", "oidn_ft", "isik", "ours")
CROP_TITLES = {"noisy": "noisy", "oidn": "OIDN", "oidn_prefilter": "OIDN, aux prefiltered",
               "oidn_ft": "OIDN fine-tuned", "isik": "Isik", "ours": "ours",
               "gt_clean": "GT_clean", "gt1": "GT1"}


def report_dir(cfg: Config, out: str | None = None) -> Path:
    if out:
        return Path(out)
    if cfg.eval.out:
        return Path(cfg.eval.out)
    return Path("reports") / (Path(cfg.runs).name or "default")


def open_store(cfg: Config) -> Store:
    store = Store(cfg.store)
    if not store.manifest_path.exists():
        raise StoreError(f"{store.root}: no dataset store here (no dataset.json); render one first "
                         f"(make dataset CONFIG=...) or point store= at it")
    store.manifest()
    return store


def _reference(store: Store, key: FrameKey, allow_gt1: bool) -> tuple[str, np.ndarray] | None:
    for name in ("gt_clean",) + (("gt1",) if allow_gt1 else ()):
        if store.image_path(key.scene, key.frame, name).exists():
            return name, store.read_image(key.scene, key.frame, name, ["color"])[0]["color"]
    return None


def frame_groups(cfg: Config, store: Store) -> dict[str, list[FrameKey]]:
    """{group: frames} with a complete frame record; dataset splits must have GT_clean.

    The hard cases (the ``stress`` presets, ``external`` scenes) are groups of their own: averaged
    into the in-distribution split they would hide how a method does on either."""
    groups: dict[str, list[FrameKey]] = {}
    splits = store.manifest()["splits"]
    if cfg.eval.split not in splits:
        raise StoreError(f"{store.manifest_path}: no split {cfg.eval.split!r} (have {', '.join(splits)})")
    hard = ([STRESS] if cfg.eval.stress else []) + [EXTERNAL]
    wanted = [cfg.eval.split] + [s for s in hard if splits.get(s) and s != cfg.eval.split]
    for split in wanted:
        keys = [k for k in store.frames(split) if store.frame_record(k.scene, k.frame) is not None]
        if split != EXTERNAL:
            cleaned = set(store.frames_with(split))
            with_clean = [k for k in keys if k in cleaned]
            if keys and not with_clean:
                raise StoreError(f"{store.root}: no {split} frame has gt_clean.exr; run `make gt-clean` first")
            keys = with_clean
        if cfg.eval.frames > 0:
            keys = keys[:cfg.eval.frames]
        if keys:
            groups[split] = keys
    if not groups:
        raise StoreError(f"{store.root}: no rendered frames in split {cfg.eval.split!r}")
    return groups


def _spp_problem(store: Store, keys: list[FrameKey], spp: int) -> str | None:
    for scene in sorted({k.scene for k in keys}):
        sm = store.scene_manifest(scene)
        n, K = int(sm["stack_spp"]), int(sm["stacks"])
        if not poolable(spp, n, K):
            return f"not in the store: {scene} has {K} stacks of {n} spp (pools {n}..{n * K} spp)"
    return None


def _summary(values: list[float]) -> dict:
    if not values:
        return {"median": None, "mean": None}
    return {"median": float(np.median(values)), "mean": float(np.mean(values))}


def _mean_metrics(rows: list[dict], names: list[str]) -> dict:
    out = {}
    for name in names:
        vals = [r["metrics"][name] for r in rows if "metrics" in r]
        out[name] = float(np.mean(vals)) if vals else None
    return out


def evaluate_group(cfg: Config, store: Store, group: str, keys: list[FrameKey], spps: list[int],
                   loader: Loader, metric_names: list[str], out_dir: Path, quiet: bool) -> dict:
    """Every method of ``eval.methods`` on the frames ``keys`` of ``group``, per spp of ``spps``.

    Returns the group's result: frames, references, render cost model and MC curves, and per spp
    (or the reason it is skipped) the method rows, equal-time MC, time vs error, comparisons and
    the names of the figures written to ``out_dir``."""
    e = cfg.eval
    opts = {"display": e.fvvdp_display}
    refs, costs, curves = _references(store, group, keys)
    result = {"frames": [str(k) for k in keys], "reference": {str(k): refs[k][0] for k in keys},
              "render_cost": {str(k): {"a": c.a, "b": c.b, "how": c.how} for k, c in costs.items()},
              "mc_curve": curves, "mc_mean": mean_curve(curves), "spp": {}}
    todo = [s for s in spps if _spp_problem(store, keys, s) is None]
    bar = progress(total=len(todo) * len(keys), desc=f"eval {group}", unit="frame", disable=quiet)
    for spp in spps:
        problem = _spp_problem(store, keys, spp)
        if problem:
            result["spp"][str(spp)] = {"skipped": problem}
            continue
        methods, rows = _load_methods(loader, e.methods, spp)
        _warm_up(methods, store, keys[0], spp)
        crops, pooled = _run_frames(e, store, keys, spp, methods, rows, refs, metric_names, opts, bar)
        _summarize_rows(rows, pooled, metric_names)
        entry = {"methods": rows, "equal_time": _equal_time(cfg, store, keys, spp, rows, refs, costs, metric_names,
                                                            opts, quiet)}
        entry["time_vs_error"] = _time_vs_error(spp, keys, rows, entry["equal_time"], costs, result["mc_mean"])
        annotate(entry, metric_names, e.bootstrap_resamples, e.bootstrap_seed)
        _figures(entry, e, group, spp, rows, crops, CROP_TITLES[refs[keys[0]][0]], metric_names, out_dir)
        result["spp"][str(spp)] = entry
    bar.close()
    return result


def _references(store: Store, group: str, keys: list[FrameKey]) -> tuple[dict, dict, dict]:
    """Per frame: (reference name, reference image), the render cost model, and (by frame name) the MC
    convergence curve against that reference."""
    refs, costs, curves = {}, {}, {}
    for key in keys:
        ref = _reference(store, key, allow_gt1=group == EXTERNAL)
        if ref is None:
            raise StoreError(f"{store.frame_dir(key.scene, key.frame)}: no reference image (gt_clean or gt1)")
        refs[key] = ref
        costs[key] = render_cost(store.frame_record(key.scene, key.frame))
        curves[str(key)] = mc_curve(store, key, ref[1], costs[key], ref[0])
    return refs, costs, curves


def _load_methods(loader: Loader, names, spp: int) -> tuple[dict, dict]:
    """(the methods that load at ``spp``, a report row for every name: available, or why not)."""
    methods, rows = {}, {}
    for name in names:
        try:
            methods[name] = loader.load(name, spp)
            rows[name] = {"label": label(name), "available": True, "device": methods[name].device,
                          "checkpoint": methods[name].checkpoint or None, "per_frame": []}
        except MethodUnavailable as exc:
            rows[name] = {"label": label(name), "available": False, "reason": str(exc)}
    return methods, rows


def realization_stacks(store: Store, key: FrameKey, spp: int, n: int) -> list[list[int]]:
    """The disjoint groups of the frame's stacks that each pool to ``spp`` (independent noise
    realizations), at most ``n`` of them, the first stacks first."""
    sm = store.scene_manifest(key.scene)
    k, total = spp // int(sm["stack_spp"]), int(sm["stacks"])
    return [list(range(g * k, (g + 1) * k)) for g in range(min(n, total // k))]


def _run_frames(e, store: Store, keys: list[FrameKey], spp: int, methods: dict, rows: dict, refs: dict,
                metric_names: list[str], opts: dict, bar) -> tuple[list, dict]:
    """Every method on every frame (on ``eval.realizations`` noise realizations of it), each frame's
    record appended to its row's ``per_frame``.

    Returns the crop grid's rows (the first ``eval.crops`` frames, first realization) and, per method
    that predicts its uncertainty, the (predicted std, actual error) pixel pairs of all frames."""
    crops, pooled = [], {}
    for i, key in enumerate(keys):
        ref = refs[key][1]
        recs = {name: [] for name in methods}
        for r, stacks in enumerate(realization_stacks(store, key, spp, e.realizations)):
            buffers = store.read(key.scene, key.frame, spp, stacks=stacks)
            outputs = {}
            for name, method in methods.items():
                method.set_frame(store, key)
                rec, outputs[name] = _score(method, buffers, ref, metric_names, opts, pooled.setdefault(name, []))
                recs[name].append(rec)
            if r == 0 and i < e.crops:
                crops.append((str(key), [outputs.get(m) for m in CROP_METHODS if m in e.methods] + [ref]))
        for name, rs in recs.items():
            rows[name]["per_frame"].append({"frame": str(key), **merge_realizations(rs, metric_names)})
        bar.update(1)
    return crops, {name: pairs for name, pairs in pooled.items() if pairs}


def _score(method, buffers: dict, ref: np.ndarray, metric_names: list[str], opts: dict, pairs: list):
    """(the record of one method on one realization, its finite output or None); the method's
    (σ, error) pixel pairs, when it predicts σ, are appended to ``pairs``."""
    oc = run_method(method, buffers)
    rec = {"seconds": oc.seconds, "status": oc.status(), "input_repaired": int(sum(oc.input_repaired.values())),
           "output_nonfinite": oc.output_nonfinite}
    if oc.output is None:
        return rec, None
    out = finite_output(oc)
    rec["metrics"] = score(out, ref, metric_names, opts)
    std = method.uncertainty()
    if std is not None:
        s, err = uncertainty.pixel_pairs(std, out, ref)
        rec["uncertainty"] = {"spearman": uncertainty.rank_correlation(s, err)}
        pairs.append((s, err))
    return rec, out


def merge_realizations(recs: list[dict], metric_names: list[str]) -> dict:
    """One frame's record from its realizations' records: the mean metrics, seconds and Spearman ρ
    over the realizations that were scored, the first failure's status, the repairs summed; a single
    realization's record unchanged."""
    if len(recs) == 1:
        return recs[0]
    scored = [r for r in recs if "metrics" in r]
    out = {"seconds": float(np.mean([r["seconds"] for r in recs])),
           "status": next((r["status"] for r in recs if r["status"] != "ok"), "ok"),
           "input_repaired": sum(r["input_repaired"] for r in recs),
           "output_nonfinite": sum(r["output_nonfinite"] for r in recs), "realizations": len(recs)}
    if scored:
        out["metrics"] = {m: float(np.mean([r["metrics"][m] for r in scored])) for m in metric_names}
    rho = [r["uncertainty"]["spearman"] for r in scored if "uncertainty" in r]
    if rho:
        out["uncertainty"] = {"spearman": float(np.mean(rho))}
    return out


def _summarize_rows(rows: dict, pooled: dict, metric_names: list[str]) -> None:
    """Add to each available method's row its means over frames: metrics, seconds, failures, repairs, uncertainty."""
    for name, row in rows.items():
        if row["available"]:
            pf = row["per_frame"]
            row["metrics"] = _mean_metrics(pf, metric_names)
            row["seconds"] = _summary([r["seconds"] for r in pf])
            row["failed_frames"] = sum(r["status"] != "ok" for r in pf)
            row["input_repaired"] = sum(r["input_repaired"] for r in pf)
            if name in pooled:
                row["uncertainty"] = uncertainty.summarize(
                    [r["uncertainty"] for r in pf if "uncertainty" in r],
                    tuple(np.concatenate(x) for x in zip(*pooled[name])))


def _figures(entry: dict, e, group: str, spp: int, rows: dict, crops: list, ref_title: str,
             metric_names: list[str], out_dir: Path) -> None:
    """Write the spp's crop grid (if any crops), uncertainty plot and per-scene figure; their names go into ``entry``."""
    titles = [CROP_TITLES[m] for m in CROP_METHODS if m in e.methods] + [ref_title]
    if crops:
        path = out_dir / f"crops_{group}_spp{spp}.png"
        report.crop_figure(crops, titles, path, e.crop_size)
        entry["crops"] = path.name
    entry["uncertainty_plot"] = uncertainty.plot(rows, out_dir / f"uncertainty_{group}_spp{spp}.png",
                                                 f"{group}, {spp} spp: predicted vs actual error")
    entry["per_scene"] = report.per_scene_figure(entry, metric_names, out_dir / f"per_scene_{group}_spp{spp}.png",
                                                 f"{group}, {spp} spp")


def _warm_up(methods: dict, store: Store, key: FrameKey, spp: int, side: int = 32) -> None:
    """One untimed call per method on a small crop: library start-up (OIDN device, torch, kernels)
    is not charged to the first frame's time."""
    crop = {k: v[:side, :side] for k, v in store.read(key.scene, key.frame, spp).items()}
    for method in methods.values():
        run_method(method, crop)


def _equal_time(cfg, store, keys, spp, rows, refs, costs, metric_names, opts, quiet) -> dict:
    e = cfg.eval
    out = {}
    if e.equal_time == "none":
        return out
    for name in e.equal_time_methods:
        row = rows.get(name)
        if not row or not row["available"] or row["seconds"]["median"] is None:
            continue
        t_d = row["seconds"]["median"]
        wanted = {k: equal_time_spp(spp, t_d, costs[k]) for k in keys}
        images = equal_time_images(cfg, store, wanted, e.equal_time, e.equal_time_max_spp, quiet)
        per_frame = []
        for key in keys:
            et = images[key]
            rec = {"frame": str(key), "wanted_spp": et.wanted, "spp": et.spp, "capped": et.capped,
                   "model_seconds": costs[key].seconds(et.spp), "measured_seconds": et.measured_seconds}
            if et.image is not None:
                rec["metrics"] = score(et.image, refs[key][1], metric_names, opts)
            else:
                rec["error"] = et.error
            per_frame.append(rec)
        out[name] = {"label": f"MC, equal time to {name}", "denoise_seconds": t_d, "mode": e.equal_time,
                     "per_frame": per_frame, "metrics": _mean_metrics(per_frame, metric_names),
                     "spp": float(np.mean([r["spp"] for r in per_frame])),
                     "wanted_spp": float(np.mean([r["wanted_spp"] for r in per_frame])),
                     "capped_frames": sum(r["capped"] for r in per_frame),
                     "failed_frames": sum("error" in r for r in per_frame)}
    return out


def _time_vs_error(spp, keys, rows, equal, costs, mc_mean) -> list[dict]:
    """One point per method: render + denoise seconds, L1, PSNR and the MC spp of equal error."""
    render_s = float(np.mean([costs[k].seconds(spp) for k in keys]))
    curve_spp = [p["spp"] for p in mc_mean]
    points = []

    def add(name, kind, seconds, m):
        if m.get("l1") is None and m.get("psnr") is None:
            return
        pt = {"method": name, "kind": kind, "seconds": seconds, "l1": m.get("l1"), "psnr": m.get("psnr")}
        if m.get("l1") is not None:
            pt["spp_equivalent_l1"] = spp_equivalent(curve_spp, [p["l1"] for p in mc_mean], m["l1"])
        if m.get("psnr") is not None:
            pt["spp_equivalent_psnr"] = spp_equivalent(curve_spp, [psnr_to_mse(p["psnr"]) for p in mc_mean],
                                                       psnr_to_mse(m["psnr"]))
        points.append(pt)

    for name, row in rows.items():
        if row["available"] and row.get("metrics"):
            kind = curve_kind(name)
            denoise = row["seconds"]["median"] if kind != "noisy" else 0.0
            add(name, kind, render_s + denoise, row["metrics"])
    for name, et in equal.items():
        secs = float(np.mean([r["model_seconds"] for r in et["per_frame"]]))
        add(f"mc_equal_{name}", "mc_equal_time", secs, et["metrics"])
    return points


def evaluate_sequence_groups(cfg: Config, store: Store, groups: dict, spps: list[int], loader: Loader,
                             metric_names: list[str], quiet: bool) -> tuple[dict, dict]:
    """``evaluate.sequence`` on the evaluated split and the external scenes (the stress presets are stills):
    ({group: result}, {group: {spp: strip}}) for the groups with a scene of two or more frames; a group whose
    frames have no camera is ``{"skipped": why}``."""
    out, strips = {}, {}
    if not cfg.eval.sequence_methods:
        return out, strips
    for group in (cfg.eval.split, EXTERNAL):
        keys = [k for seq in sequences(groups.get(group, [])).values() for k in seq]
        if not keys:
            continue
        try:
            for k in keys:
                store.camera(k.scene, k.frame)
        except StoreError as exc:
            out[group] = {"skipped": str(exc)}
            print(f"note: no sequence page for {group}: {exc}", flush=True)
            continue
        n = len(keys)
        names = {k: _reference_name(store, k, group == EXTERNAL) for k in keys}
        bar = progress(total=n * len(spps), desc=f"sequences {group}", unit="frame", disable=quiet)
        out[group], strips[group] = evaluate_sequences(
            cfg, store, keys, names.get, [s for s in spps if _spp_problem(store, keys, s) is None], loader,
            lambda k, spp: realization_stacks(store, k, spp, 1)[0], metric_names, bar)
        bar.close()
    return out, strips


def _reference_name(store: Store, key: FrameKey, allow_gt1: bool) -> str:
    return "gt_clean" if store.image_path(key.scene, key.frame, "gt_clean").exists() or not allow_gt1 else "gt1"


def run_eval(cfg: Config, spps: list[int] | None = None, scenes: list[str] | None = None, out: str | None = None,
             quiet: bool = False, defines: dict[str, str] | None = None) -> dict:
    t0 = time.perf_counter()
    e = cfg.eval
    check_names(e.methods)
    check_sequence_names(e.sequence_methods)
    check_metrics(e.metrics)
    spps = [int(s) for s in (spps or e.spp)]
    if not spps or any(s < 1 for s in spps):
        raise ConfigError(f"eval.spp: expected positive sample counts, got {spps!r}")
    store = open_store(cfg) if not scenes else None
    if scenes:
        from mcdenoise.render.external import render_scene
        for xml in scenes:
            render_scene(xml, cfg.store, cfg, defines=defines)
        store = open_store(cfg)
    groups = frame_groups(cfg, store)
    if scenes:
        from mcdenoise.render.external import scene_id
        named = {scene_id(x, None) for x in scenes}
        groups[EXTERNAL] = [k for k in groups.get(EXTERNAL, []) if k.scene in named]
    metric_names, missing = usable_metrics(e.metrics)
    out_dir = report_dir(cfg, out)
    out_dir.mkdir(parents=True, exist_ok=True)
    # Temporary files of a report write a kill interrupted (one eval per report folder: all stale).
    for tmp in out_dir.glob(".*.tmp"):
        tmp.unlink(missing_ok=True)
    loader = Loader(cfg)
    result = {"meta": report.run_meta(cfg, spps), "metrics": metric_names,
              "metrics_missing": {**missing, **NOT_COMPUTED}, "groups": {}}
    for group, keys in groups.items():
        result["groups"][group] = evaluate_group(cfg, store, group, keys, spps, loader, metric_names, out_dir, quiet)
    result["sequences"], strips = evaluate_sequence_groups(cfg, store, groups, spps, loader, metric_names, quiet)
    result["meta"]["seconds"] = time.perf_counter() - t0
    result["stability"] = report.load_stability(out_dir)
    write_sequence_page(result["sequences"], strips, out_dir, e.bootstrap_resamples, e.bootstrap_seed)
    text = report.write_eval(result, out_dir)
    if not quiet:
        print(text)
    n_frames = sum(len(g["frames"]) for g in result["groups"].values())
    print(f"eval: {n_frames} frames in {len(result['groups'])} group(s) x spp {','.join(map(str, spps))} x "
          f"{len(e.methods)} methods in {result['meta']['seconds']:.1f} s -> {out_dir}/eval.md", flush=True)
    return result
