"""The evaluation along camera moves: each scene of the evaluated split as a sequence of its frames.

Per scene, spp and method (``eval.sequence_methods``), the frames are denoised in order, on the
first noise realization (the first stacks pooled to the spp; consecutive frames are separate
renders, so their noise is independent). Per frame: PSNR, L1 and HDR-FLIP against the reference
(GT_clean), and from the second frame on the temporal instability (``pipeline.temporal``): the
output's frame-to-frame change against the reference's, over the pixels valid in both. Per scene:
FovVideoVDP on the sequence as a video (``eval.sequence_fps``), when pyfvvdp is installed.

Two warps, for two purposes:

- a method sees only what a renderer gives it: the history of a temporal method is reprojected with
  the noisy input's own depth and normal (as a user's frame would be);
- the metric warps with GT1's depth and normal, so that the instability of every method is measured
  through the same motion.

Methods: every per-frame name of ``eval.methods`` (``evaluate.methods``), and
``oidn_prefilter_temporal``: ``oidn_prefilter``'s output blended with its own warped history
(``pipeline.temporal.blend_history``, weight ``eval.temporal_weight`` on the new frame, history
clamped to the new output's 3×3 range), the temporal filter a user could build in an afternoon;
``ours_filter``: the same filter on ``ours``' outputs (what ``denoise --sequence`` runs for a model that does
not read the past); ``ours_temporal``: the model loaded for ``ours`` given its own previous output warped into
this frame (``Denoiser.denoise(history=...)``, what ``denoise --sequence`` runs for it), available when that
model reads the past (``diffusion.history``). Frame 1 of a temporal method is its per-frame method's output
(no history yet), reported apart.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.config import Config, ConfigError
from mcdenoise.pipeline.store import FrameKey, Store

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
    """ConfigError naming an unknown method of ``eval.sequence_methods``."""
    check_names([n for n in names if n not in TEMPORAL], "eval.sequence_methods")
    dup = sorted({n for n in names if n in TEMPORAL and names.count(n) > 1})
    if dup:
        raise ConfigError(f"eval.sequence_methods: {', '.join(dup)} listed twice")


def sequences(store: Store, keys: list[FrameKey]) -> dict[str, list[FrameKey]]:
    """{scene: its frames in order} for the scenes of ``keys`` with at least two frames."""
    by_scene: dict[str, list[FrameKey]] = {}
    for k in keys:
        by_scene.setdefault(k.scene, []).append(k)
    return {s: sorted(ks, key=lambda k: k.frame) for s, ks in by_scene.items() if len(ks) > 1}


@dataclass
class Frame:
    """What the sequence loop needs of one frame: its input, reference, camera and both warps' geometry."""
    key: FrameKey
    buffers: dict
    reference: np.ndarray
    camera: motion.Camera
    geometry: dict = field(default_factory=dict)       # "input" / "gt1": (depth, normal)


def read_frame(store: Store, key: FrameKey, spp: int, stacks: list[int], ref_name: str) -> Frame:
    buffers = store.read(key.scene, key.frame, spp, stacks=stacks)
    reference = store.read_image(key.scene, key.frame, ref_name, ["color"])[0]["color"]
    gt = store.read_image(key.scene, key.frame, "gt1", ["depth", "normal"])[0]
    return Frame(key, buffers, reference, store.camera(key.scene, key.frame),
                 {"input": (buffers["depth"][..., 0], buffers["normal"]), "gt1": (gt["depth"][..., 0], gt["normal"])})


def motion_between(cur: Frame, prev: Frame, which: str) -> tuple[np.ndarray, np.ndarray]:
    """(positions in ``prev`` of ``cur``'s pixels, validity), from the ``which`` geometry of both frames."""
    depth, normal = cur.geometry[which]
    depth_prev, normal_prev = prev.geometry[which]
    return motion.reproject(depth, cur.camera, prev.camera, depth_prev=depth_prev, normal_t=normal,
                            normal_prev=normal_prev)


def score_sequence(frames_out: dict[str, list[np.ndarray | None]], frames: list[Frame], names: list[str],
                   opts: dict) -> dict:
    """Per method: per-frame metrics ``names``, and from frame 2 on the temporal instability."""
    out: dict[str, list[dict]] = {}
    warps = [None] + [motion_between(frames[t], frames[t - 1], "gt1") for t in range(1, len(frames))]
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


def run_sequence(store: Store, seq: list[FrameKey], spp: int, stacks_of, methods: dict, ref_name: str,
                 weight: float) -> tuple[dict, dict, list[Frame]]:
    """Every method along one sequence: ({method: [output per frame]}, {method: [seconds per frame]}, frames)."""
    frames: list[Frame] = []
    outputs: dict[str, list] = {n: [] for n in methods}
    outputs.update({n: [] for n in TEMPORAL_FILTERS if TEMPORAL_FILTERS[n] in methods})
    outputs.update({n: [] for n, base in LEARNED.items() if reads_history(methods.get(base))})
    seconds: dict[str, list] = {n: [] for n in outputs}
    for t, key in enumerate(seq):
        fr = read_frame(store, key, spp, stacks_of(key), ref_name)
        frames.append(fr)
        for name, method in methods.items():
            method.set_frame(store, key)
            oc = run_method(method, fr.buffers)
            outputs[name].append(finite_output(oc) if oc.output is not None else None)
            seconds[name].append(oc.seconds)
        for name, base in TEMPORAL_FILTERS.items():
            if name not in outputs:
                continue
            y, history = outputs[base][t], outputs[name][t - 1] if t > 0 else None
            if y is None or history is None:
                outputs[name].append(y)
            else:
                xy, valid = motion_between(fr, frames[t - 1], "input")
                outputs[name].append(temporal.blend_history(y, motion.warp(history, xy, valid), valid, weight))
            seconds[name].append(seconds[base][t])
        for name, base in LEARNED.items():
            if name not in outputs:
                continue
            history = outputs[name][t - 1] if t > 0 else None
            if history is None:     # no history yet: the model's single-frame output, which ``base`` is
                outputs[name].append(outputs[base][t])
                seconds[name].append(seconds[base][t])
                continue
            xy, valid = motion_between(fr, frames[t - 1], "input")
            oc = run_method(methods[base], fr.buffers, history=(motion.warp(history, xy, valid), valid))
            outputs[name].append(finite_output(oc) if oc.output is not None else None)
            seconds[name].append(oc.seconds)
    return outputs, seconds, frames


def reads_history(method) -> bool:
    """Whether a loaded method is a model that reads the past (``train.infer.Denoiser.history``)."""
    return bool(getattr(getattr(method, "denoiser", None), "history", False))


def load_sequence_methods(loader: Loader, names: list[str], spp: int) -> tuple[dict, dict]:
    """(per-frame methods that load, including those the temporal filters need; a row per name)."""
    methods, rows = {}, {}
    for name in names:
        base = TEMPORAL.get(name, name)
        try:
            if base not in methods:
                methods[base] = loader.load(base, spp)
            if name in LEARNED and not reads_history(methods[base]):
                raise MethodUnavailable(f"the model of {base} ({methods[base].checkpoint}) does not read history: "
                                        "train one with diffusion.history=true (ours_filter is the temporal filter "
                                        "on it)")
            suffix = " reading its previous output" if name in LEARNED else " + temporal filter" if name != base else ""
            rows[name] = {"label": label(base) + suffix, "available": True,
                          "checkpoint": methods[base].checkpoint or None}
        except MethodUnavailable as exc:
            rows[name] = {"label": name, "available": False, "reason": str(exc)}
    return methods, rows


def summarize(per_frame: list[dict], names: list[str]) -> dict:
    """Means over frame 1 and over frames 2.. of the per-frame records of one method."""
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
    per-scene video FovVideoVDP, and means over frame 1 and frames 2..; and per spp the first scene's frames
    and outputs, to draw the strip from."""
    e = cfg.eval
    seqs = sequences(store, keys)
    names = [m for m in SEQUENCE_METRICS if m in metric_names]
    result = {"scenes": {s: [str(k) for k in ks] for s, ks in seqs.items()}, "spp": {},
              "weight": e.temporal_weight, "metrics": names}
    strips = {}
    for spp in spps:
        methods, rows = load_sequence_methods(loader, e.sequence_methods, spp)
        for name in rows:
            rows[name].update(per_frame=[], video={})
        strip = None
        for scene, seq in seqs.items():
            outputs, seconds, frames = run_sequence(store, seq, spp, lambda k: stacks_for(k, spp), methods,
                                                    ref_name(seq[0]), e.temporal_weight)
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
