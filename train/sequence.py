"""``denoise --sequence``: a rendered sequence, every frame denoised and blended with its warped history.

    python -m pipeline denoise --sequence 'in/frame_####.exr' --out 'out/####.exr'
    python -m pipeline denoise --sequence 'data/default/scenes/ext_room/###/s00.exr' --out 'out/room_###.exr'

Each frame's noisy diffuse light is first averaged over it, the frames before it (``--temporal-window``,
default ``eval.temporal_window``: 8 frames) and those after it (``--ahead``, default ``eval.temporal_ahead``: 7;
0 for frames that arrive one at a time), each
reprojected, a past pixel counting where it agrees within
``eval.temporal_gate`` standard deviations; ``pipeline.temporal.average_input``; frames
without the light components, a plain beauty, are not averaged; frames without variance layers, a Cycles render
whose light passes give the components, average the diffuse light divided by the albedo instead,
``temporal.averaging_kind``). Then the frame is denoised as ``denoise
--exr`` does (``--method ours`` or ``oidn_prefilter``), and the temporal filter of ``pipeline.temporal``
blends it with the previous output brought into this frame (``pipeline.motion``: the renderer's motion
vectors, or the frame's depth and the two cameras), where the history is valid:

    out_t = w · y_t + (1 − w) · clamp(warp(out_{t−1}))        (w: ``--temporal-weight``, default
                                                              ``eval.temporal_weight``)

and, when the frames after are read (``--ahead`` above 0), with the history of both sides: the mean of that one
and of the same filter run backwards from the frames after (``temporal.filtered``), each clamped; a frame is
then written once the ``--ahead`` frames after it are denoised.

A model folder that reads the past (``diffusion.history``: its model.json's condition has the history
channels) needs no filter: it is given its own previous output warped into this frame, with the validity
mask, as condition channels (``Denoiser.denoise(history=...)``), and its output is the frame's output. Either
way a frame is one ``pipeline.temporal.step``, as in the sequence evaluation. The summary line says which ran.

The motion comes from one of two things in every EXR:

* **motion vectors**: Blender's ``Vector`` pass (``ViewLayer.Vector.X/Y/Z/W``, enable it under View Layer
  Properties → Passes → Data; Cycles writes it with motion blur off). They follow moving objects too. A pixel's
  history is valid where the previous frame's vectors lead back to it and, with the Z pass (``Depth.Z``), the
  depth there agrees (``motion.flow``); the frames after are followed along the vectors' other half.
* **the camera and depth**: the standard header attributes ``worldToCamera`` and ``worldToNDC``
  (``render-scene`` writes them; so do renderers that follow OpenEXR's camera attributes), a depth channel
  ``Z`` (camera-space z) and a display window (the camera's image) the size of the pixels. Static scenes only.

A frame with neither is denoised alone, and the command says so in one line. The first frame has no history.
The outputs are independent of where the sequence is cut only up to that first frame: run the whole shot at once.
"""
from __future__ import annotations

import glob
import re
import time
from collections import deque
from pathlib import Path

import numpy as np

from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.config import Config, weight_problem
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.exr import StoreError, read_camera, read_layers, write_output
from mcdenoise.pipeline.progress import progress

_HASHES = re.compile(r"#+")


def _hash_run(pattern: str, flag: str) -> re.Match:
    runs = list(_HASHES.finditer(pattern))
    if len(runs) != 1:
        raise TrainError(f"{flag} {pattern!r}: expected one run of # for the frame number, e.g. 'in/frame_####.exr'")
    return runs[0]


def sequence_files(pattern: str) -> list[tuple[int, Path]]:
    """The files of ``pattern`` (one run of ``#`` in the file name or a folder: the zero-padded frame number, as
    many digits as ``#``), as (frame number, path) in frame order; TrainError when none exists."""
    run = _hash_run(pattern, "--sequence")
    digits = run.end() - run.start()
    head, tail = pattern[:run.start()], pattern[run.end():]
    rx = re.compile(re.escape(head) + f"([0-9]{{{digits}}})" + re.escape(tail))
    found = sorted((int(m.group(1)), Path(f)) for f in glob.glob(glob.escape(head) + "[0-9]" * digits + glob.escape(tail))
                   if (m := rx.fullmatch(f)) and Path(f).is_file())
    if not found:
        raise TrainError(f"--sequence {pattern!r}: no file matches")
    return found


def output_path(pattern: str, number: int) -> Path:
    """``pattern`` with its run of ``#`` replaced by ``number``, zero-padded to the run's length."""
    run = _hash_run(pattern, "--out")
    return Path(pattern[:run.start()] + str(number).zfill(run.end() - run.start()) + pattern[run.end():])


def frame_view(path: Path, buffers: dict, vectors: np.ndarray | None = None) -> tuple[motion.View | None, str]:
    """(the frame's view, '') when the EXR has a Vector pass (``vectors``, as ``read_layers`` gives it in
    ``passes``), or the camera attributes, a depth channel and a display window the size of its pixels; else
    (None, why)."""
    height, width = buffers["color"].shape[:2]
    camera, why = _camera(path, buffers, (height, width))
    if vectors is not None:
        depth = buffers["depth"][..., 0] if "depth" in buffers else None
        return motion.View(camera, depth, buffers.get("normal"), motion.from_blender_vectors(vectors)), ""
    if camera is None:
        return None, f"{why}, and no Vector pass"
    return motion.View.of(camera, buffers), ""


def _camera(path: Path, buffers: dict, size: tuple[int, int]) -> tuple[motion.Camera | None, str]:
    """(the EXR's camera, '') when it has the camera attributes, a depth channel and a display window of ``size``
    (H, W), else (None, why)."""
    if "depth" not in buffers:
        return None, "no depth channel Z"
    try:
        cam = read_camera(path)
    except StoreError as exc:
        return None, str(exc).removeprefix(f"{path}: ")
    # the camera projects onto the display window, the pixels are the data window: a crop or an overscan
    # would reproject every pixel to the wrong place
    if (cam.height, cam.width) != size:
        return None, f"display window {cam.width}x{cam.height} differs from the pixels' {size[1]}x{size[0]}"
    return cam, ""


def per_frame_denoiser(cfg: Config, method: str, spp: int, model: Path | None, device: str | None, precision: str,
                       seed: int | None):
    """((buffers, history) -> HDR, the weights' name, whether it reads the history itself, the set of what the
    frames lacked that the model reads, filled as frames are denoised) of ``method``: ours (the model folder; it
    reads the history where its model.json says so), or OIDN's final-frame mode."""
    from . import oidn
    from .infer import load_denoiser, weights_text
    from .model import find_run

    lacked: set[str] = set()
    if method == "oidn_prefilter":
        return (lambda b, _: oidn.denoise({k: b[k] for k in ("color", "albedo", "normal")}, aux=True, clean_aux=True),
                "pyoidn built-in rt_hdr_calb_cnrm_large on albedo and normal prefiltered by OIDN", False, lacked)
    if method != "ours":
        raise TrainError(f"--sequence runs --method ours or oidn_prefilter, not {method}")
    folder = model or find_run(cfg, spp)
    den = load_denoiser(folder, device or cfg.diffusion.device, False, precision)
    learned = den.history

    def run(b, history):
        y = den.denoise(b, int(spp), skip=None, seed=cfg.seed if seed is None else seed, history=history)
        # as denoise --exr says it: what the model had to leave to OIDN
        if den.last_black:
            lacked.add("a black input frame is written black")
        elif den.last_estimate_only:
            lacked.add(f"no albedo/normal layers: {den.fallback} alone")
        elif den.last_base_only:
            lacked.add("colour, albedo and normal only (no variance, light components or material layers): "
                       "the model's base, OIDN, alone")
        return y
    return run, weights_text(folder, den.meta), learned, lacked


def _temporal_settings(cfg: Config, weight: float | None, window: int | None,
                       ahead: int | None) -> tuple[float, int, int]:
    """(--temporal-weight, --temporal-window, --ahead), the config's where not given; TrainError naming a bad one."""
    weight = cfg.eval.temporal_weight if weight is None else float(weight)
    if (why := weight_problem(weight)) is not None:
        raise TrainError(f"--temporal-weight: {why}")
    window = cfg.eval.temporal_window if window is None else int(window)
    if window < 1:
        raise TrainError(f"--temporal-window: must be >= 1 (1: no averaging), got {window}")
    ahead = cfg.eval.temporal_ahead if ahead is None else int(ahead)
    if ahead < 0:
        raise TrainError(f"--ahead: must be >= 0 (0: the frames before alone), got {ahead}")
    return weight, window, ahead


def _frames_ahead(files: list, i: int, ahead: int, cache: dict, window: temporal.InputWindow) -> list:
    """[(what ``window`` averages of a frame, its view)] of the ``ahead`` frames after frame ``i`` of ``files``,
    read once each into ``cache`` (only those layers are held: the frame is read whole again at its turn)."""
    for j in [j for j in cache if j <= i]:
        del cache[j]
    for j in range(i + 1, min(i + 1 + ahead, len(files))):
        if j not in cache:
            passes: dict = {}
            buffers = read_layers(files[j][1], passes=passes)
            cache[j] = window.keep(buffers), frame_view(files[j][1], buffers, passes.get("Vector"))[0]
    return [cache[j] for j in range(i + 1, min(i + 1 + ahead, len(files)))]


def _outputs(files: list, out_pattern: str) -> list[Path]:
    """The output path of each of ``files``; TrainError when one of them is an input."""
    outs = [output_path(out_pattern, n) for n, _ in files]
    inputs = {p.resolve() for _, p in files}
    clash = next((o for o in outs if o.resolve() in inputs), None)
    if clash is not None:
        raise TrainError(f"--out {out_pattern}: {clash} is one of the inputs; name other files (the inputs stay)")
    return outs


def _averaged_frames(files: list, outs: list, window: temporal.InputWindow, ahead: int, seen: dict, quiet: bool):
    """Per frame in order: (its path, its output path, its input averaged over ``window`` and the ``ahead`` frames
    after, its view); ``seen`` counts the frames without motion ("alone": the first's why) and without diffuse
    light layers ("bare")."""
    cache: dict = {}
    for i, ((_, path), out) in enumerate(progress(list(zip(files, outs)), desc="denoise sequence", unit="frame",
                                                  disable=quiet)):
        passes: dict = {}
        buffers = read_layers(path, passes=passes)
        view, why = frame_view(path, buffers, passes.get("Vector"))
        seen["alone"] = seen["alone"] or (f"{path}: {why}" if view is None else "")
        seen["bare"] += not all(n in buffers for n in temporal.AVERAGED["diffuse"])     # nothing to average there
        yield path, out, window.take(buffers, view, _frames_ahead(files, i, ahead, cache, window)), view


def _learned(run, frames):
    """((path, out, view), output, the history's validity) per frame of a model reading its previous output."""
    previous = None
    for path, out, averaged, view in frames:
        hdr, valid = temporal.step(run, averaged, view, previous)
        previous = hdr, view
        yield (path, out, view), hdr, valid


def _filtered(run, frames, weight: float, ahead: int):
    """((path, out, view), output, the history's validity) per frame of a per-frame method and the filter
    (``temporal.filtered``), each once the ``ahead`` frames after it are denoised."""
    kept: deque = deque()               # (path, out, view) of the frames denoised and not yet filtered

    def outputs():
        for path, out, averaged, view in frames:
            kept.append((path, out, view))
            yield run(averaged, None), view
    for hdr, valid in temporal.filtered(outputs(), weight, ahead):
        yield kept.popleft(), hdr, valid


def cmd_denoise_sequence(cfg: Config, pattern: str, out_pattern: str, spp: int | None, method: str = "ours",
                         weight: float | None = None, quiet: bool = False, model: Path | None = None,
                         device: str | None = None, precision: str = "auto", seed: int | None = None,
                         window: int | None = None, ahead: int | None = None, kind: str | None = None) -> int:
    """Denoise every file of ``pattern`` in frame order into ``out_pattern`` (module docstring). ``kind``: what the
    input averaging averages (``temporal.GATE_GROUPS``); None: ``temporal.averaging_kind`` of the first frame."""
    weight, window, ahead = _temporal_settings(cfg, weight, window, ahead)
    files = sequence_files(pattern)
    outs = _outputs(files, out_pattern)
    if spp is None:
        from .infer import exr_spp
        spp, how = exr_spp(files[0][1])
        if not quiet:
            print(f"{files[0][1]}: {spp} spp ({how}; pass --spp to say otherwise)", flush=True)
    first = read_layers(files[0][1])
    if method == "oidn_prefilter" and not {"albedo", "normal"} <= first.keys():
        raise TrainError(f"--method oidn_prefilter prefilters albedo and normal, but {files[0][1]} has only "
                         f"{', '.join(sorted(first))}; use --method ours")
    run, weights, learned, lacked = per_frame_denoiser(cfg, method, spp, model, device, precision, seed)
    kind = temporal.averaging_kind(first) if kind is None else kind
    inputs_window = temporal.InputWindow(window, kind, gate=cfg.eval.temporal_gate or None, ahead=ahead)
    took, seen, t0 = [], {"alone": "", "bare": 0}, time.perf_counter()
    frames = _averaged_frames(files, outs, inputs_window, ahead, seen, quiet)
    # a model that reads its own previous output has no filter after it; the filter reads both sides with ``ahead``
    done = _learned(run, frames) if learned else _filtered(run, frames, weight, ahead)
    for (path, out, view), hdr, valid in done:
        if valid is not None:
            took.append(float(valid.mean()))
        out.parent.mkdir(parents=True, exist_ok=True)
        temporal_record = {"learned": True} if learned else {"weight": weight, "both_sides": ahead > 0}
        write_output(out, hdr, {"image": "denoised", "source": str(path), "spp": int(spp), "method": method,
                                "weights": weights, "temporal": {**temporal_record, "history_fraction":
                                                                 None if valid is None else float(valid.mean())}},
                     camera=None if view is None else view.camera)
    alone, bare = seen["alone"], seen["bare"]
    if alone:
        print(f"note: {alone}: no motion for that frame, so it was denoised alone", flush=True)
    how = (f"{method} reading its own warped previous output (learned history)" if learned
           else f"{method} + temporal filter{' on both sides' if ahead else ''}, weight {weight:g}")
    if (window > 1 or ahead) and bare == len(files):
        how += ", input not averaged (no frame has diffuse light layers)"
    elif window > 1 or ahead:
        how += (f", diffuse light{' ÷ albedo' if kind in temporal.DEMODULATED else ''} averaged over up to {window} "
                f"frames and {ahead} after"
                + (f" ({np.mean(inputs_window.counts):.1f} per pixel)" if inputs_window.counts else "")
                + (f" ({bare} of {len(files)} frames have no diffuse light layers: those not)" if bare else ""))
    print(f"denoised {len(files)} frames of {pattern} ({spp} spp, {how}; "
          f"history on {len(took)} of {len(files)} frames"
          + (f", {100 * float(np.mean(took)):.0f} % of their pixels" if took else "")
          + f") with {weights} in {time.perf_counter() - t0:.1f} s -> {out_pattern}"
          + "".join(f"; {note}" for note in sorted(lacked)), flush=True)
    return 0
