"""``denoise --sequence``: a rendered sequence, every frame denoised and blended with its warped history.

    python -m pipeline denoise --sequence 'in/frame_####.exr' --out 'out/####.exr'
    python -m pipeline denoise --sequence 'data/default/scenes/ext_room/###/s00.exr' --out 'out/room_###.exr'

Each frame is denoised as ``denoise --exr`` does (``--method ours`` or ``oidn_prefilter``), then the
temporal filter of ``pipeline.temporal`` blends it with the previous output brought into this frame
(``pipeline.motion``: the frame's depth and the two cameras), where the history is valid:

    out_t = w · y_t + (1 − w) · clamp(warp(out_{t−1}))        (w: ``--temporal-weight``, default
                                                              ``eval.temporal_weight``)

A model folder that reads the past (its model.json ``history``, ``diffusion.history``) needs no filter: it
is given its own previous output warped into this frame, with the validity mask, as condition channels
(``Denoiser.denoise(history=...)``), and its output is the frame's output. The summary line says which ran.

The motion needs, in every EXR, the standard header attributes ``worldToCamera`` and ``worldToNDC``
(``render-scene`` writes them; so do renderers that follow OpenEXR's camera attributes) and a depth
channel ``Z`` (camera-space z). A frame without them is denoised alone, and the command says so in one
line. The first frame has no history. The outputs are independent of where the sequence is cut only up
to that first frame: run the whole shot at once.
"""
from __future__ import annotations

import glob
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.config import Config
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


@dataclass
class Seen:
    """What the next frame needs of this one: its output, camera and geometry (None: no motion)."""
    output: np.ndarray
    camera: motion.Camera | None
    depth: np.ndarray | None
    normal: np.ndarray | None


def frame_geometry(path: Path, buffers: dict) -> tuple[motion.Camera | None, str]:
    """(the frame's camera, '') when the EXR has the camera attributes and a depth channel, else (None, why)."""
    if "depth" not in buffers:
        return None, "no depth channel Z"
    try:
        return read_camera(path), ""
    except StoreError as exc:
        return None, str(exc).removeprefix(f"{path}: ")


def history_of(cam, buffers: dict, prev: Seen | None) -> tuple[np.ndarray, np.ndarray] | None:
    """(the previous output warped into this frame, its validity), None without a previous frame or motion."""
    if prev is None or cam is None or prev.camera is None:
        return None
    xy, valid = motion.reproject(buffers["depth"][..., 0], cam, prev.camera, depth_prev=prev.depth,
                                 normal_t=buffers.get("normal"), normal_prev=prev.normal)
    return motion.warp(prev.output, xy, valid), valid


def blend(y: np.ndarray, history: tuple[np.ndarray, np.ndarray] | None, weight: float
          ) -> tuple[np.ndarray, float | None]:
    """(this frame's output, the fraction of its pixels that took history; None without history)."""
    if history is None:
        return y, None
    warped, valid = history
    return temporal.blend_history(y, warped, valid, weight), float(valid.mean())


def per_frame_denoiser(cfg: Config, method: str, spp: int, model: Path | None, device: str | None, precision: str,
                       seed: int | None):
    """((buffers, history) -> HDR, the weights' name, whether it reads the history itself) of ``method``: ours
    (the model folder; it reads the history where its model.json says so), or OIDN's final-frame mode."""
    from . import oidn
    from .infer import load_denoiser, weights_text
    from .model import find_run

    if method == "oidn_prefilter":
        return (lambda b, _: oidn.denoise({k: b[k] for k in ("color", "albedo", "normal")}, aux=True, clean_aux=True),
                "pyoidn built-in rt_hdr_calb_cnrm_large on albedo and normal prefiltered by OIDN", False)
    if method != "ours":
        raise TrainError(f"--sequence runs --method ours or oidn_prefilter, not {method}")
    folder = model or find_run(cfg, spp)
    den = load_denoiser(folder, device or cfg.diffusion.device, False, precision)
    learned = den.history

    def run(b, history):
        return den.denoise(b, int(spp), skip=None, seed=cfg.seed if seed is None else seed,
                           history=history if learned else None)
    return run, weights_text(folder, den.meta), learned


def cmd_denoise_sequence(cfg: Config, pattern: str, out_pattern: str, spp: int | None, method: str = "ours",
                         weight: float | None = None, quiet: bool = False, model: Path | None = None,
                         device: str | None = None, precision: str = "auto", seed: int | None = None) -> int:
    """Denoise every file of ``pattern`` in frame order into ``out_pattern`` (module docstring)."""
    weight = cfg.eval.temporal_weight if weight is None else float(weight)
    if not 0.0 < weight <= 1.0:
        raise TrainError(f"--temporal-weight {weight}: expected a share of the new frame in (0, 1]")
    files = sequence_files(pattern)
    outs = [output_path(out_pattern, n) for n, _ in files]
    inputs = {p.resolve() for _, p in files}
    clash = next((o for o in outs if o.resolve() in inputs), None)
    if clash is not None:
        raise TrainError(f"--out {out_pattern}: {clash} is one of the inputs; name other files (the inputs stay)")
    if spp is None:
        from .infer import exr_spp
        spp, how = exr_spp(files[0][1])
        if not quiet:
            print(f"{files[0][1]}: {spp} spp ({how}; pass --spp to say otherwise)", flush=True)
    first = read_layers(files[0][1])
    if method == "oidn_prefilter" and not {"albedo", "normal"} <= first.keys():
        raise TrainError(f"--method oidn_prefilter prefilters albedo and normal, but {files[0][1]} has only "
                         f"{', '.join(sorted(first))}; use --method ours")
    run, weights, learned = per_frame_denoiser(cfg, method, spp, model, device, precision, seed)
    prev, took, alone, t0 = None, [], "", time.perf_counter()
    for (number, path), out in progress(list(zip(files, outs)), desc="denoise sequence", unit="frame", disable=quiet):
        buffers = read_layers(path)
        cam, why = frame_geometry(path, buffers)
        alone = alone or (f"{path}: {why}" if cam is None else "")
        history = history_of(cam, buffers, prev)
        if learned:     # the model reads its own previous output: no filter after it
            hdr = run(buffers, history)
            valid = None if history is None else float(history[1].mean())
        else:
            hdr, valid = blend(run(buffers, None), history, weight)
        if valid is not None:
            took.append(valid)
        out.parent.mkdir(parents=True, exist_ok=True)
        temporal_record = {"learned": True} if learned else {"weight": weight}
        write_output(out, hdr, {"image": "denoised", "source": str(path), "spp": int(spp), "method": method,
                                "weights": weights, "temporal": {**temporal_record, "history_fraction": valid}},
                     camera=cam)
        prev = Seen(hdr, cam, buffers["depth"][..., 0] if cam is not None else None,
                    buffers.get("normal") if cam is not None else None)
    if alone:
        print(f"note: {alone}: no motion for that frame, so it was denoised alone", flush=True)
    how = (f"{method} reading its own warped previous output (learned history)" if learned
           else f"{method} + temporal filter, weight {weight:g}")
    print(f"denoised {len(files)} frames of {pattern} ({spp} spp, {how}; "
          f"history on {len(took)} of {len(files) - 1} frames"
          + (f", {100 * float(np.mean(took)):.0f} % of their pixels" if took else "")
          + f") with {weights} in {time.perf_counter() - t0:.1f} s -> {out_pattern}", flush=True)
    return 0
