"""The evaluation along camera moves: each scene of the evaluated split as a sequence of its frames.

A sequence is a run of consecutive frames of one scene (``sequences``: each frame's previous frame is
``FrameKey.previous``); a frame missing from the evaluated frames (no record, no GT_clean) cuts its scene
in two. Per sequence, spp and method (``eval.sequence_methods``), the frames are denoised in order, on the
first noise realization (the first stacks pooled to the spp; consecutive frames are separate
renders, so their noise is independent). Per frame: PSNR, L1 and HDR-FLIP against the reference
(GT_clean), and from t = 1 on the temporal instability (``pipeline.temporal``): the output's
frame-to-frame change against the reference's, over the pixels valid in both. Per sequence:
FovVideoVDP on it as a video (``eval.sequence_fps``), when pyfvvdp is installed.

Two warps, for two purposes:

- a method sees only what a renderer gives it: the history of a temporal method is reprojected with
  the noisy input's own depth and normal (as a user's frame would be);
- the metric warps with GT1's depth and normal, so that the instability of every method is measured
  through the same motion.

Methods: every per-frame name of ``eval.methods`` (``evaluate.methods``), and
``oidn_prefilter_temporal``: ``oidn_prefilter``'s output blended with its own warped history
(``pipeline.temporal.filtered``, weight ``eval.temporal_weight`` on the new frame, history
clamped to the new output's 3×3 range; with ``eval.temporal_ahead`` the history of both sides), the temporal
filter a user could build in an afternoon;
``ours_filter``: the same filter on ``ours``' outputs (what ``denoise --sequence`` runs for a model that does
not read the past); ``ours_temporal``: the model loaded for ``ours`` given its own previous output warped into
this frame (``Denoiser.denoise(history=...)``, what ``denoise --sequence`` runs for it), available when that
model reads the past (``diffusion.history``). A temporal method runs as in ``denoise --sequence``: the filter
(``pipeline.temporal.filtered``) on its base's outputs, or one ``pipeline.temporal.step`` a frame; without a
history (t = 0 without frames after it, or after a frame where the method failed) it is its per-frame method's
output on the frame's input as the temporal methods average it (without frames on either side, the per-frame
output itself). t = 0 is reported apart. Only the
methods listed run, with the per-frame methods their temporal ones build on.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.store import FrameKey, Store, frame_name

from .harness import finite_output, run_method
from .methods import Loader, MethodUnavailable, check_names, label
from .scoring import score

# of eval.metrics, those the sequence tables show (PSNR always)
SEQUENCE_METRICS = ("psnr", "l1", "hdr_flip")
# temporal method -> the per-frame method whose outputs it filters (``ours_temporal`` is what
# ``denoise --sequence`` runs)
TEMPORAL_FILTERS = {"oidn_prefilter_temporal": "oidn_prefilter", "ours_filter": "ours"}
# learned temporal method -> the per-frame method whose model reads its own warped previous output
LEARNED = {"ours_temporal": "ours"}
TEMPORAL = {**TEMPORAL_FILTERS, **LEARNED}


def check_sequence_names(names: list[str]) -> None:
    """ConfigError naming an unknown or repeated method of ``eval.sequence_methods``."""
    check_names(names, "eval.sequence_methods", tuple(TEMPORAL))


def sequences(keys: list[FrameKey]) -> dict[str, list[FrameKey]]:
    """{name: frames} for the runs of ``keys`` of two or more frames, each frame after the first one the next of
    its previous frame (``FrameKey.previous``): a frame missing from ``keys`` (not rendered, no gt_clean) cuts its
    scene in two runs, so no frame is scored against one that is not its previous frame. A run is named by its
    scene, or ``scene/first-last`` (frame numbers) where the scene has several."""
    by_scene: dict[str, set[FrameKey]] = {}
    for k in keys:
        by_scene.setdefault(k.scene, set()).add(k)
    out = {}
    for scene, frames in by_scene.items():
        found: list[list[FrameKey]] = []
        for k in sorted(frames, key=lambda k: k.frame):
            if found and found[-1][-1] == k.previous():
                found[-1].append(k)
            else:
                found.append([k])
        found = [run for run in found if len(run) > 1]
        for run in found:
            out[scene if len(found) == 1 else f"{run[0]}-{frame_name(run[-1].frame)}"] = run
    return out


@dataclass
class Frame:
    """What the sequence loop needs of one frame: its input, reference, and both warps' views."""
    key: FrameKey
    buffers: dict
    reference: np.ndarray
    views: dict = field(default_factory=dict)       # "input" / "gt1": motion.View with that image's depth, normal


def read_frame(store: Store, key: FrameKey, spp: int, stacks: list[int], ref_name: str) -> Frame:
    buffers = store.read(key.scene, key.frame, spp, stacks=stacks)
    reference = store.read_image(key.scene, key.frame, ref_name, ["color"])[0]["color"]
    gt = store.read_image(key.scene, key.frame, "gt1", ["depth", "normal"])[0]
    camera = store.camera(key.scene, key.frame)
    return Frame(key, buffers, reference, {"input": motion.View.of(camera, buffers), "gt1": motion.View.of(camera, gt)})


def score_sequence(frames_out: dict[str, list[np.ndarray | None]], frames: list[Frame], names: list[str],
                   opts: dict) -> dict:
    """Per method: per-frame metrics ``names``, and from t = 1 on the temporal instability."""
    out: dict[str, list[dict]] = {}
    warps = [None] + [motion.reproject_view(frames[t].views["gt1"], frames[t - 1].views["gt1"])
                      for t in range(1, len(frames))]
    for name, outputs in frames_out.items():
        recs = []
        for t, (fr, y) in enumerate(zip(frames, outputs)):
            if y is None:
                recs.append({"frame": str(fr.key)})
                continue
            rec = {"frame": str(fr.key), "metrics": score(y, fr.reference, names, opts)}
            if t > 0 and outputs[t - 1] is not None:
                xy, valid = warps[t]
                rec["metrics"]["instability"] = temporal.instability(
                    y, motion.warp(outputs[t - 1], xy, valid), fr.reference,
                    motion.warp(frames[t - 1].reference, xy, valid), valid)
                rec["valid_fraction"] = float(valid.mean())
            recs.append(rec)
        out[name] = recs
    return out


def run_sequence(store: Store, seq: list[FrameKey], spp: int, stacks_of, methods: dict, temporal_names: list[str],
                 ref_name: str, weight: float, window: int = 1, gate: float = 0.0,
                 ahead: int = 0) -> tuple[dict, dict, list[Frame]]:
    """Along one sequence, every per-frame method of ``methods`` and the temporal methods ``temporal_names`` (their
    bases among ``methods``, their input averaged over ``window`` frames and the ``ahead`` frames after, with
    ``gate``; the filter on both sides with ``ahead``): ({method: [output per frame]}, {method: [seconds per
    frame]}, frames)."""
    frames = [read_frame(store, key, spp, stacks_of(key), ref_name) for key in seq]
    outputs: dict[str, list] = {n: [] for n in [*methods, *temporal_names]}
    seconds: dict[str, list] = {n: [] for n in outputs}
    # the input averaged once per frame, for every temporal method
    inputs_window = temporal.InputWindow(window, gate=gate or None, ahead=ahead)
    for t, fr in enumerate(frames):
        key = seq[t]
        for name, method in methods.items():
            method.set_frame(store, key)
            oc = run_method(method, fr.buffers)
            outputs[name].append(finite_output(oc) if oc.output is not None else None)
            seconds[name].append(oc.seconds)
        t0 = time.perf_counter()
        later = [(inputs_window.keep(f.buffers), f.views["input"]) for f in frames[t + 1:t + 1 + ahead]]
        averaged = inputs_window.take(fr.buffers, fr.views["input"], later) if temporal_names else fr.buffers
        averaging = time.perf_counter() - t0       # every temporal method's, which each would pay alone
        for name in temporal_names:
            base = TEMPORAL[name]
            previous = (outputs[name][t - 1], frames[t - 1].views["input"]) if t > 0 and name in LEARNED else None
            y, secs = temporal_frame(methods[base], outputs[base][t], seconds[base][t], fr, averaged, previous)
            outputs[name].append(y)
            seconds[name].append(secs + averaging)
    for name in temporal_names:
        if name in TEMPORAL_FILTERS:    # the per-frame outputs on the averaged input, filtered along the sequence
            t0 = time.perf_counter()
            outputs[name] = [y for y, _ in temporal.filtered(zip(outputs[name], [f.views["input"] for f in frames]),
                                                             weight, ahead)]
            share = (time.perf_counter() - t0) / len(frames)
            seconds[name] = [s + share for s in seconds[name]]
    return outputs, seconds, frames


def temporal_frame(method, base_output: np.ndarray | None, base_seconds: float, fr: Frame, buffers: dict,
                   previous=None) -> tuple[np.ndarray | None, float]:
    """One frame of a temporal method's base ``method`` on the frame's input ``buffers`` (averaged over the
    neighbouring frames), and its seconds. ``previous`` (a model that reads the past: its output of the frame
    before and that frame's view): one ``temporal.step``, the history warped with the input's own depth and normal;
    None: the method's per-frame output, which the filter then blends (``temporal.filtered``), its output on the
    frame's own input (``base_output``, ``base_seconds``) reused rather than run again."""
    inside = {"wall": 0.0, "method": 0.0}      # the time spent in ``denoise``, and the method's share of it

    def denoise(given, history):
        if history is None and given is fr.buffers:
            inside["method"] += base_seconds
            return base_output
        t0 = time.perf_counter()
        oc = run_method(method, given, history=history)
        inside["wall"] += time.perf_counter() - t0
        inside["method"] += oc.seconds
        return finite_output(oc) if oc.output is not None else None

    t0 = time.perf_counter()
    y, _ = temporal.step(denoise, buffers, fr.views["input"], previous)     # no previous: no history
    return y, time.perf_counter() - t0 - inside["wall"] + inside["method"]


def load_sequence_methods(loader: Loader, names: list[str], spp: int, window: int = 1,
                          ahead: int = 0) -> tuple[dict, dict]:
    """(the per-frame methods the available rows need: theirs or their temporal method's base; a row per name;
    ``window``, ``ahead``: the frames up to and after this one that a temporal method averages the input over,
    said in its label)."""
    methods, rows = {}, {}
    for name in names:
        base = TEMPORAL.get(name, name)
        try:
            if base not in methods:
                methods[base] = loader.load(base, spp)
            # the loaded model's condition has the history channels (``train.model.reads_history``)
            if name in LEARNED and not getattr(getattr(methods[base], "denoiser", None), "history", False):
                raise MethodUnavailable(f"the model of {base} ({methods[base].checkpoint}) does not read history: "
                                        "train one with diffusion.history=true (ours_filter is the temporal filter "
                                        "on it)")
            how = temporal.describe_averaging(window, ahead) if name != base else None
            averaged = f" on the {how}" if how else ""
            suffix = averaged + (" reading its previous output" if name in LEARNED
                                 else " + temporal filter" + (" on both sides" if ahead else "") if name != base
                                 else "")
            rows[name] = {"label": label(base) + suffix, "available": True,
                          "checkpoint": methods[base].checkpoint or None}
        except MethodUnavailable as exc:
            rows[name] = {"label": name, "available": False, "reason": str(exc)}
    needed = {TEMPORAL.get(n, n) for n, row in rows.items() if row["available"]}
    return {n: m for n, m in methods.items() if n in needed}, rows


def summarize(per_frame: list[dict], names: list[str]) -> dict:
    """Means over t = 0 ("first") and over t ≥ 1 ("later") of the per-frame records of one method."""
    def mean(recs, key):
        vals = [r["metrics"][key] for r in recs if "metrics" in r and key in r["metrics"]]
        vals = [v for v in vals if np.isfinite(v)]
        return float(np.mean(vals)) if vals else None

    firsts = [r for r in per_frame if r.get("index") == 0]
    later = [r for r in per_frame if r.get("index", 0) > 0]
    return {"first": {m: mean(firsts, m) for m in names},
            "later": {m: mean(later, m) for m in (*names, "instability")}}


def evaluate_sequences(cfg: Config, store: Store, keys: list[FrameKey], ref_name, spps: list[int],
                       loader: Loader, stacks_for, metric_names: list[str], bar=None) -> tuple[dict, dict]:
    """The sequence result of ``keys`` (frames of one group): per spp, per method, per-frame records,
    per-sequence video FovVideoVDP, and means over t = 0 and t ≥ 1; and per spp the first sequence's frames and
    outputs, to draw the strip from."""
    e = cfg.eval
    seqs = sequences(keys)
    names = [m for m in SEQUENCE_METRICS if m in metric_names]
    result = {"scenes": {s: [str(k) for k in ks] for s, ks in seqs.items()}, "spp": {},
              "weight": e.temporal_weight, "window": e.temporal_window, "ahead": e.temporal_ahead,
              "gate": e.temporal_gate, "metrics": names}
    strips = {}
    for spp in spps:
        methods, rows = load_sequence_methods(loader, e.sequence_methods, spp, e.temporal_window,
                                              e.temporal_ahead)
        for name in rows:
            rows[name].update(per_frame=[], video={})
        strip = None
        for scene, seq in seqs.items():
            outputs, seconds, frames = run_sequence(store, seq, spp, lambda k: stacks_for(k, spp), methods,
                                                    [n for n in rows if n in TEMPORAL and rows[n]["available"]],
                                                    ref_name(seq[0]), e.temporal_weight, e.temporal_window,
                                                    e.temporal_gate, e.temporal_ahead)
            scored = score_sequence({n: outputs[n] for n in rows if rows[n]["available"]}, frames, names,
                                    {"display": e.fvvdp_display})
            for name, recs in scored.items():
                for i, rec in enumerate(recs):
                    rows[name]["per_frame"].append({**rec, "index": i, "seconds": seconds[name][i]})
                rows[name]["video"][scene] = video_quality(outputs[name], frames, e)
            if strip is None:
                strip = {"scene": scene, "frames": frames, "outputs": outputs}
            if bar is not None:
                bar.update(len(seq))
        for row in rows.values():
            if row["available"]:
                row["mean"] = summarize(row["per_frame"], names)
        result["spp"][str(spp)] = {"methods": rows, "metrics": names}
        strips[str(spp)] = strip
    return result, strips


def video_quality(outputs: list, frames: list[Frame], e) -> float | None:
    """FovVideoVDP (JOD) of the sequence as a video at ``eval.sequence_fps``; None without pyfvvdp or with a
    frame that did not run."""
    if "fvvdp" not in e.metrics or any(y is None for y in outputs):
        return None
    from mcdenoise.pipeline.metrics import fvvdp_video
    try:
        return fvvdp_video(outputs, [f.reference for f in frames], e.fvvdp_display, e.sequence_fps)
    except ImportError:
        return None
