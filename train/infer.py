"""Inference: denoise a frame with a trained model folder (a run or ``train/shipped``), and σ's calibration.

    den = load_denoiser(find_run(cfg, 4))                  # or base_only=True: the ablation row
    hdr = den.denoise(store.read(scene, frame, 4), spp=4, seed=0)          # (H, W, 3) float32
    hdr, std = den.denoise(buffers, spp=4, samples=8, with_std=True)       # mean of 8 and their std
    hdr = den.denoise(buffers, spp=4, history=(warped_prev_output, valid))  # a model that reads the past

What the model cannot represent is said, not hidden: non-finite input values are replaced by 0
(``last_repaired``), an all-black input is returned black (``last_black``), an input without albedo
and normal gets OIDN on what there is (``last_estimate_only``), pixels past OIDN's output range are
clamped (``last_clamped``).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch

from mcdenoise.pipeline.config import Config, pick_device
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.exr import StoreError, write_output
from mcdenoise.pipeline.numerics import repair_nonfinite, shorten_normals

from . import oidn
from .model import (
    NETWORK,
    ControlledOIDN,
    clean_aux,
    find_run,
    inputs,
    load,
    network_output,
    oidn_ft_blob,
    present,
)
from .sampler import Formulation, check_strength, sample, with_strength

if TYPE_CHECKING:   # the store is imported where a store frame is read: ``denoise --exr`` needs none
    from mcdenoise.pipeline.store import FrameKey

PRECISIONS = {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}

# ---- uncertainty -------------------------------------------------------------------------------

SIGMA_STEPS, SIGMA_SAMPLES = 3, 4     # the sampling the evaluator's uncertainty row uses (ours_s3_k4)


def calibrate(refiner: "Denoiser", items: list[dict], seed: int = 0) -> dict:
    """One scale for the samples' per-pixel standard deviation, fitted on validation images: the
    median of |error| / σ over the pixels with σ > 0, divided by 0.6745 (the median of |N(0, 1)|), so a
    Gaussian error with the scaled σ has half its pixels within 0.6745 σ. Robust to the heavy tails of
    rendering errors, unlike a least-squares fit. Fitted at the refiner's ``strength``, which scales both
    the mean's change and the samples' spread, but not the error by the same factor."""
    ratios = []
    for it in items:
        H, W = it["ref"].shape[:2]
        hdr, s = refiner.refine(torch.as_tensor(it["x"]), torch.as_tensor(it["cond"]), it["scale"], H, W,
                                SIGMA_STEPS, 0, None, seed, SIGMA_SAMPLES, refiner.strength)
        e = np.abs(hdr - it["ref"]).mean(2).ravel()
        s = s.mean(2).ravel()
        ratios.append(e[s > 0] / s[s > 0])
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    scale = float(np.median(r) / 0.6745) if r.size else 1.0
    return {"scale": scale, "steps": SIGMA_STEPS, "samples": SIGMA_SAMPLES, "pixels": int(r.size),
            "strength": refiner.strength}


class Denoiser:
    """A trained model folder as the evaluator and ``denoise`` use it."""

    clamp_note = "pixels beyond OIDN's output range (65504 after exposure) clamped to its end"   # with last_clamped

    def __init__(self, model: ControlledOIDN, meta: dict, device, base_only: bool = False, folder: Path | None = None,
                 precision: str = "auto"):
        """``precision``: 'fp32', 'fp16' or 'bf16' autocast of the networks; 'auto' is fp16 on CUDA (it agrees
        with fp32 at about 70 dB), fp32 elsewhere."""
        device = torch.device(device)
        self.model, self.meta, self.device, self.folder = model, meta, device, folder
        self.precision = ("fp16" if device.type == "cuda" else "fp32") if precision == "auto" else precision
        if self.precision not in PRECISIONS:
            raise TrainError(f"precision {precision!r}: expected auto, {', '.join(PRECISIONS)}")
        self.formulation = Formulation.from_record(meta["formulation"])
        self.sigma_scale = float((meta.get("sigma") or {}).get("scale", 1.0))
        self.clean_aux = clean_aux(meta)   # a _calb_cnrm base reads albedo and normal prefiltered by OIDN
        if base_only:
            self.model.control = None
        self.name = "base_only" if base_only else "ours"
        # the model reads the previous output warped into this frame (``denoise(history=)``): its condition
        # has the history channels (``load_model`` built it from model.json's ``cond_channels``)
        self.history = bool(model.history)
        # model.json ``control_without_groups: false``: on colour, albedo and normal alone (none of GROUPS: an
        # EXR from another renderer) the base runs alone, where validation found the Control Module worse
        self.control_without_groups = bool(meta.get("control_without_groups", True))
        # model.json ``strength`` (``export --strength``): how much of the Control Module's change it applies
        self.strength = check_strength(meta.get("strength", 1.0), f"{folder or 'the model'}/model.json: strength")
        self.last_repaired = self.last_clamped = 0
        self.last_black = self.last_estimate_only = self.last_base_only = False
        self.last_shortened = 0        # normals longer than 1 scaled to unit length (garbage layers)
        self.last_seconds = 0.0
        self.fallback = ""

    def denoise(self, buffers: dict[str, np.ndarray], spp: int, skip: int | None = None, seed: int = 0,
                steps: int | None = None, start: str | None = None, samples: int = 1, with_std: bool = False,
                strength: float | None = None, history: tuple[np.ndarray, np.ndarray] | None = None):
        """HDR (H, W, 3) float32 (and the per-pixel std of ``samples`` samples with ``with_std``);
        ``strength``: the fraction of the Control Module's change applied (default: the model's); ``history``:
        (the previous frame's output warped into this one (H, W, 3), its (H, W) validity), for a model that reads
        the past (``self.history``); None (a first frame, a single frame) is served as a frame without it."""
        if history is not None:
            if not self.history:
                raise TrainError(f"{self.folder or 'this model'} does not read history (its model.json's "
                                 "cond_channels have no history channels)")
            from .history import with_history  # the motion code is read only where there is a history
            buffers = with_history(buffers, history)
        strength = self.strength if strength is None else check_strength(strength, "strength")
        t0 = time.perf_counter()
        buffers = {k: np.array(v, dtype=np.float32, copy=True) for k, v in buffers.items()}
        self.last_repaired = sum(repair_nonfinite(buffers).values())
        self.last_clamped, self.last_base_only = 0, False
        self.last_shortened = shorten_normals(buffers["normal"]) if "normal" in buffers else 0
        color = buffers["color"]
        self.last_black = not np.any(color)
        self.last_estimate_only = not all(a in buffers for a in ("albedo", "normal"))
        if self.last_black:
            hdr = std = np.zeros_like(color)
        elif self.last_estimate_only:   # the base reads albedo and normal: OIDN on what there is
            hdr, std = self._oidn_only(buffers), np.zeros_like(color)
        else:
            self.last_base_only = not self.control_without_groups and not any(present(buffers).values())
            hdr, std = self._sample(buffers, spp, skip, seed, steps, start, samples, strength)
        self.last_seconds = time.perf_counter() - t0
        return (hdr, std) if with_std else hdr

    def _oidn_only(self, buffers: dict[str, np.ndarray]) -> np.ndarray:
        """OIDN on the layers there are: with the model folder's fine-tuned weights for them
        (``oidn_ft/<network>.tza``, OIDN fine-tuned on our data) when it has them, else OIDN's own."""
        network = oidn.network_for("albedo" in buffers, False)
        blob_path = oidn_ft_blob(self.folder, network) if self.folder is not None else None
        self.fallback = str(blob_path) if blob_path is not None and blob_path.exists() else f"OIDN {network}"
        blob = blob_path.read_bytes() if blob_path is not None and blob_path.exists() else None
        return oidn.denoise({k: v for k, v in buffers.items() if k in ("color", "albedo")}, weights=blob)

    def autocast(self):
        """The networks' precision (a no-op context in fp32)."""
        return torch.autocast(self.device.type, dtype=PRECISIONS[self.precision], enabled=self.precision != "fp32")

    def _sample(self, buffers, spp, skip, seed, steps, start, samples, strength=1.0):
        # off the CPU, OIDN's aux prefilter runs on the device too (its PyTorch twin)
        x, cond, scale = inputs(buffers, int(spp), clean_aux=self.clean_aux,
                                aux_device=None if self.device.type == "cpu" else str(self.device), history=self.history)
        H, W = buffers["color"].shape[:2]
        control = self.model.control
        if self.last_base_only:
            self.model.control = None
        try:
            hdr, std_hdr = self.refine(torch.from_numpy(x)[None], torch.from_numpy(cond)[None], scale, H, W, steps,
                                       skip, start, seed, samples, strength)
        finally:
            self.model.control = control
        return hdr, std_hdr * self.sigma_scale

    def refine(self, x: torch.Tensor, cond: torch.Tensor, scale: float, H: int, W: int, steps, skip, start, seed,
               samples, strength: float) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) HDR and the samples' unscaled per-pixel std for OIDN-space inputs (``inputs``, batch of
        one): ``sample``, then ``strength`` of the Control Module's change; what ``denoise`` returns and
        ``calibrate`` fits σ on."""
        with self.autocast():
            mean, std, est = sample(self.model, x.to(self.device), cond.to(self.device), self.formulation, steps, skip,
                                    start, seed, samples)
        mean, std = with_strength(mean.float(), std.float(), est.float(), strength)
        # OIDN's output space ends at 1 (PU of float16's largest value, 65504 after exposure); a Control
        # Module pushed past it by inputs unlike its training would overflow the inverse
        # transfer to inf: such pixels are clamped to the range's end and counted.
        self.last_clamped = int((mean[..., :H, :W] > 1.0).any(dim=1).sum())
        return self.to_hdr(mean.clamp(max=1.0), std, scale, H, W)

    @staticmethod
    def to_hdr(mean: torch.Tensor, std: torch.Tensor, scale: float, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) HDR of an OIDN-space mean and its std (times the local slope of the inverse transfer)."""
        hdr = network_output(mean, scale, (H, W))
        slope = (network_output(mean + 1e-4, scale, (H, W)) - hdr) / 1e-4
        as_image = lambda t: np.ascontiguousarray(t[0].permute(1, 2, 0).float().cpu().numpy())  # noqa: E731
        return as_image(hdr), as_image(slope.abs() * std[..., :H, :W])


def load_denoiser(folder: str | Path, device: str = "auto", base_only: bool = False, precision: str = "auto") -> Denoiser:
    dev = pick_device(device)
    model, meta = load(folder, dev)
    return Denoiser(model, meta, dev, base_only, Path(folder), precision)


# ---- The denoise command: a store frame or an EXR, with ours or OIDN itself ----------------------
# The ``denoise`` and ``pack`` commands of ``python -m pipeline``.
#
# denoise (--frame SCENE/FRAME | --exr FILE)  → cmd_denoise(...)         an EXR with the denoised colour
#                                               cmd_denoise_oidn(...)    the same with OIDN itself
# pack                                        → cmd_pack(cfg, splits)    <runs>/pack/<split>_oidn_base*.safetensors
DEFAULT_EXR_SPP = 16


def exr_spp(path: Path) -> tuple[int, str]:
    """The sample count an EXR's mcdenoise header records, or the renderer's (Cycles'), else ``DEFAULT_EXR_SPP``
    (the middle of 4..64)."""
    from mcdenoise.pipeline.exr import read_header, renderer_samples
    try:
        spp = read_header(path).get("spp")
    except StoreError:
        spp = None
    if isinstance(spp, int) and spp > 0:
        return spp, "from its header"
    if (spp := renderer_samples(path)) is not None:
        return spp, "from Cycles' header"
    return DEFAULT_EXR_SPP, "not recorded in the file: assumed"


def _warn_if_correlated(exr: str, color: np.ndarray) -> None:
    """A warning on stderr when the input's noise is spatially correlated (train/infer.py)."""
    ratio = correlated_noise(color)
    if ratio is not None:
        print(f"warning: {exr}: its noise looks spatially correlated (neighbour ratio {ratio:.2f} < "
              f"{CORRELATED_BELOW}), as a wide reconstruction filter makes it (Mitsuba's default 'gaussian', "
              "'tent'; Cycles' Blackman-Harris); OIDN, this denoiser's first estimate, leaves such noise in place. Render "
              "with a box filter one pixel wide (Mitsuba: <rfilter type=\"box\"/> in the film; Cycles: Film > Pixel "
              "Filter > Box, width 1 px); a nearly noise-free image can read this way too.",
              file=sys.stderr, flush=True)


def check_output(out: str, exr: str | None) -> None:
    """``--out`` names a new file: not the input (the user's render would be overwritten), not a folder."""
    if exr is not None and Path(out).resolve() == Path(exr).resolve():
        raise TrainError(f"--out {out}: that is the input; name another file (the input stays as it is)")
    if Path(out).is_dir():
        raise TrainError(f"--out {out}: a folder, expected the name of the EXR file to write")


def weights_text(folder: Path, meta: dict) -> str:
    """How a line names a model folder: its path (relative to the working folder where it is inside it) and
    what it is, e.g. ``train/shipped (Control Module on OIDN rt_hdr_calb_cnrm_large)``."""
    path = Path(folder).resolve()
    shown = path.relative_to(Path.cwd()) if path.is_relative_to(Path.cwd()) else path
    return f"{shown} (Control Module on OIDN {meta.get('base_network', NETWORK)})"


def cmd_denoise(cfg: Config, spp: int, frame: str | None, exr: str | None, out: str, skip: int | None,
                seed: int | None, base_only: bool = False, quiet: bool = False, steps: int | None = None,
                samples: int | None = None, ensemble: int = 1, strength: float | None = None,
                device: str | None = None, precision: str = "auto", model: Path | None = None) -> int:
    """Denoise one frame of the store (``SCENE/FRAME``) or one EXR and write ``out`` (EXR: ``color``, the
    mean of ``samples`` samples, and ``std``, their per-pixel standard deviation); ``ensemble``: the mean of
    both over that many flipped and transposed copies (``self_ensemble``); ``strength``: the fraction of
    the Control Module's change applied (default: the model's); ``model``: the model folder (default: the config's
    run for ``spp``, ``find_run``). The input is read (and refused in one line) before anything else is said or
    loaded; the output names the weights that ran."""
    if (frame is None) == (exr is None):
        raise TrainError("give exactly one of --frame SCENE/FRAME or --exr FILE")
    if frame is not None and spp is None:
        raise TrainError("--frame needs --spp (which of the store's sample counts to denoise)")
    check_output(out, exr)
    samples = cfg.diffusion.samples if samples is None else int(samples)
    if samples < 1:
        raise TrainError(f"--samples {samples}: expected at least 1")
    buffers, source, camera = _read_input(cfg, frame, exr, spp)
    if spp is None:
        spp, how = exr_spp(Path(exr))
        if not quiet:
            print(f"{exr}: {spp} spp ({how}; pass --spp to say otherwise)", flush=True)
    folder = model or find_run(cfg, spp)
    den = load_denoiser(folder, device or cfg.diffusion.device, base_only, precision)

    def run(b):   # colour and std side by side, so that one self-ensemble turns both back
        return np.concatenate(den.denoise(b, int(spp), skip=skip, seed=cfg.seed if seed is None else seed,
                                          steps=steps, samples=samples, with_std=True, strength=strength), axis=2)
    t0 = time.perf_counter()
    out6 = self_ensemble(run, buffers, ensemble)
    hdr, std, seconds = out6[..., :3], out6[..., 3:], time.perf_counter() - t0
    meta = {"image": "denoised", "source": source, "spp": int(spp), "method": den.name,
            "weights": weights_text(folder, den.meta), "skip": den.formulation.skip if skip is None else skip,
            "steps": steps, "samples": samples, **_outcome(den), "ensemble": ensemble,
            "strength": den.strength if strength is None else strength, "seconds": round(seconds, 3)}
    write_output(Path(out), hdr, meta, layers={"std": std}, camera=camera)
    if not quiet:
        print(_denoised_line(den, buffers, meta, hdr.shape, out), flush=True)
    return 0


def _outcome(den: Denoiser) -> dict:
    """What the last ``denoise`` call of ``den`` met in its input, for the output's header record."""
    return {"formulation": den.formulation.record(), "repaired_nonfinite": den.last_repaired,
            "clamped_pixels": den.last_clamped, "black_input": den.last_black,
            "estimate_only": den.last_estimate_only, "fallback": den.fallback, "base_only": den.last_base_only,
            "shortened_normals": den.last_shortened}


def _denoised_line(den: Denoiser, buffers: dict, meta: dict, shape: tuple, out: str) -> str:
    """The one line ``denoise`` ends with: what ran on what, in how long, where it went, what it had to do."""
    ensemble, repaired = meta["ensemble"], den.last_repaired
    alone = (f"; no albedo/normal layers: {den.fallback} on the colour{' and albedo' if 'albedo' in buffers else ''}"
             if den.fallback else "; no variance/albedo/normal layers: the first estimate (OIDN) alone")
    return (f"denoised {meta['source']} ({shape[1]}x{shape[0]}, {meta['spp']} spp, {den.name}"
            f"{f', self-ensemble of {ensemble}' if ensemble > 1 else ''}) with {meta['weights']} in "
            f"{meta['seconds']:.1f} s -> {out}" + (f"; {repaired} non-finite input values replaced by 0" if repaired
                                                  else "") + (alone if den.last_estimate_only else "")
            + ("; colour, albedo and normal only: the model's base alone (its model.json: control_without_groups)"
               if den.last_base_only else ""))


def oidn_weights_for(cfg: Config, network: str) -> tuple[bytes, str]:
    """(the TZA blob, where it came from) that ``denoise --method oidn_ft`` runs for ``network``: the
    config's oidn_ft run of that network."""
    from mcdenoise.pipeline.config import run_dir as model_dir

    from .baselines.oidn_ft import export_blob, load_run
    folder = model_dir(cfg, "oidn_ft", variant=network)
    if (folder / "model.safetensors").exists():
        return export_blob(load_run(folder, cfg)[0]), str(folder)
    raise TrainError(f"no oidn_ft run for OIDN's {network} network in {folder}: train it with "
                     f"`make train MODEL=oidn_ft SPP=any oidn_ft.network={network}`, or give --oidn-weights FILE.tza")


def _card_network(weights_file: str) -> str:
    """The network named by the card ``export --format oidn`` writes beside a .tza (``<file>.json``); ''."""
    card = Path(weights_file).with_suffix(".json")
    try:
        return str(json.loads(card.read_text()).get("network", "")) if card.is_file() else ""
    except (OSError, ValueError):
        return ""


def cmd_denoise_oidn(cfg: Config, frame: str | None, exr: str | None, out: str, method: str,
                     weights_file: str | None, spp: int | None = None, quiet: bool = False, ensemble: int = 1) -> int:
    """Denoise a store frame or an EXR with OIDN itself: its built-in network (``oidn``), its final-frame
    mode with the aux prefiltered (``oidn_prefilter``, on albedo and normal), an oidn_ft run (``oidn_ft``)
    or the weights of ``weights_file``, on the layers the input has (colour; +albedo; +albedo+normal), at
    OIDN's speed. ``oidn_ft_prefilter``, and a ``weights_file`` whose card names a ``_calb_cnrm`` network,
    run in the final-frame mode."""
    from mcdenoise.pipeline.weights import read_tza
    
    from .model import UNet

    if (frame is None) == (exr is None):
        raise TrainError("give exactly one of --frame SCENE/FRAME or --exr FILE")
    check_output(out, exr)
    buffers, source, camera = _read_input(cfg, frame, exr, spp)
    # OIDN spreads a NaN/Inf over its receptive field: lost samples count as 0, as in every denoiser here
    buffers = {k: np.array(v, dtype=np.float32, copy=True) for k, v in buffers.items()}
    repaired = sum(repair_nonfinite(buffers).values())
    layers = [a for a in ("albedo", "normal") if a in buffers]
    layers = layers if layers and layers[0] == "albedo" else []
    network = oidn.network_for("albedo" in layers, "normal" in layers)
    clean_aux = (method in ("oidn_prefilter", "oidn_ft_prefilter") and not weights_file
                 or bool(weights_file) and oidn.clean_aux(_card_network(weights_file)))
    if clean_aux and len(layers) < 2:
        what = f"--method {method}" if not weights_file else f"{weights_file} (OIDN's final-frame network)"
        raise TrainError(f"{what} prefilters albedo and normal, but {source} has only "
                         f"{', '.join(['colour', *layers])}; use --method oidn")
    blob, origin = None, ("pyoidn built-in rt_hdr_calb_cnrm_large on albedo and normal prefiltered by OIDN"
                          if clean_aux else f"pyoidn built-in {network}")
    if weights_file:
        blob, origin = oidn.weights_blob(network, weights_file), weights_file
        need = (UNet.from_tza(read_tza(blob, weights_file)).in_channels - 3) // 3
        if need > len(layers):
            raise TrainError(f"{weights_file}: these OIDN weights read {3 + 3 * need} channels (colour"
                             f"{', albedo' if need else ''}{', normal' if need > 1 else ''}), but {source} has only "
                             f"{', '.join(['colour', *layers])}")
        layers = layers[:need]
    elif method == "oidn_ft":
        blob, origin = oidn_weights_for(cfg, network)
    elif method == "oidn_ft_prefilter":
        blob, origin = oidn_weights_for(cfg, "rt_hdr_calb_cnrm_large")
    t = time.perf_counter()
    hdr = self_ensemble(lambda b: oidn.denoise(b, aux=bool(layers), weights=blob, clean_aux=clean_aux),
                        {"color": buffers["color"], **{a: buffers[a] for a in layers}}, ensemble)
    seconds = time.perf_counter() - t
    meta = {"image": "denoised", "source": source, "method": method, "weights": origin,
            "inputs": ["color", *layers], "ensemble": ensemble, "repaired_nonfinite": repaired,
            "seconds": round(seconds, 3)}
    write_output(Path(out), hdr, meta, camera=camera)
    if not quiet:
        print(f"denoised {source} ({hdr.shape[1]}x{hdr.shape[0]}; {', '.join(['colour', *layers])}) with OIDN "
              f"({origin}) in {seconds:.2f} s -> {out}"
              + (f"; {repaired} non-finite input values replaced by 0" if repaired else ""), flush=True)
    return 0


def _read_input(cfg: Config, frame: str | None, exr: str | None, spp: int | None) -> tuple[dict, str, object]:
    """The buffers of ``--frame SCENE/FRAME`` (at ``spp``) or ``--exr FILE``, how to name the source, and its
    camera (None where it records none), which the output keeps."""
    if exr is not None:
        from mcdenoise.pipeline.exr import read_camera, read_layers
        aliased: dict = {}
        buffers = read_layers(Path(exr), aliased)
        for name, channels in aliased.items():
            layers = dict.fromkeys(c.rsplit(".", 1)[0] for c in channels)       # in order, once each
            print(f"{exr}: {name} from {', '.join(map(repr, layers))}"
                  + (f" ({', '.join(channels)})" if len(layers) == 1 else ""), flush=True)
        _warn_if_correlated(exr, buffers["color"])
        try:
            camera = read_camera(Path(exr))
        except StoreError:      # most EXRs have no camera attributes: nothing to keep
            camera = None
        return buffers, exr, camera
    if spp is None:
        raise TrainError("--frame needs --spp (which of the store's sample counts to denoise)")
    from mcdenoise.pipeline.store import Store

    store, key = Store(cfg.store), _frame_key(frame)
    buffers = store.read(key.scene, key.frame, int(spp))
    try:
        camera = store.camera(key.scene, key.frame)
    except StoreError:
        camera = None
    return buffers, f"{store.root}/{frame}", camera


def _frame_key(frame: str) -> FrameKey:
    """``--frame SCENE/FRAME`` as a store key."""
    from mcdenoise.pipeline.store import FrameKey

    try:
        scene, idx = frame.split("/")
        return FrameKey(scene, int(idx))
    except ValueError:
        raise TrainError(f"--frame {frame!r}: expected SCENE/FRAME, e.g. s00000/000") from None


# ---- Self-ensembling over the dihedral group -----------------------------------------------------
# Self-ensembling over the dihedral group: a denoiser run on flipped and transposed copies of a frame,
# each output turned back and the outputs averaged (Lim et al. 2017's "geometric self-ensemble").
#
# A CNN denoiser is not equivariant to flips and transposes, so its errors on the eight copies of a
# frame are partly independent and their mean has less of them; the image itself is unchanged by the
# round trip (``invert_transform(apply_transform(x, t), t) == x``, tested). Every buffer moves with the pixels and vectors
# are not turned: OIDN's training augmentation flips and transposes normals the same way, so each copy
# is an input the network has seen the like of. The cost is ``n`` runs of the denoiser.
#
#     self_ensemble(fn, buffers, n)    the mean of fn(buffers) over the first n of TRANSFORMS (1, 2, 4 or 8)
# (transpose, flip rows, flip columns): the identity first, then the transforms that add most to it.
TRANSFORMS = ((False, False, False), (False, False, True), (False, True, False), (False, True, True),
              (True, False, False), (True, False, True), (True, True, False), (True, True, True))
ENSEMBLE_SIZES = (1, 2, 4, 8)


def apply_transform(image: np.ndarray, t: tuple[bool, bool, bool]) -> np.ndarray:
    """(H, W, ...) ``image`` transposed, then flipped as ``t`` says."""
    transpose, flip_y, flip_x = t
    out = image.swapaxes(0, 1) if transpose else image
    out = out[::-1] if flip_y else out
    return out[:, ::-1] if flip_x else out


def invert_transform(image: np.ndarray, t: tuple[bool, bool, bool]) -> np.ndarray:
    """The inverse of ``apply_transform(·, t)``: undo the flips, then the transpose."""
    transpose, flip_y, flip_x = t
    out = image[:, ::-1] if flip_x else image
    out = out[::-1] if flip_y else out
    return out.swapaxes(0, 1) if transpose else out


def self_ensemble(fn: Callable[[dict[str, np.ndarray]], np.ndarray], buffers: dict[str, np.ndarray],
             n: int) -> np.ndarray:
    """The mean of ``fn`` over the first ``n`` transforms of every (H, W, C) buffer, each output turned back."""
    if n not in ENSEMBLE_SIZES:
        raise ValueError(f"a self-ensemble of {n} copies: expected one of {ENSEMBLE_SIZES}")
    total = None
    for t in TRANSFORMS[:n]:
        out = invert_transform(fn({k: np.ascontiguousarray(apply_transform(v, t)) for k, v in buffers.items()}), t)
        total = out.astype(np.float64) if total is None else total + out
    return (total / n).astype(np.float32)


# ---- Spatially correlated noise in an input (a wide reconstruction filter) -----------------------
# Is the noise of an image independent from pixel to pixel? (``denoise --exr``'s input check.)
#
# OIDN, and every denoiser here that starts from it, expects each sample to land in one pixel (a box
# reconstruction filter, as this project's renderer uses). A wide filter (Mitsuba's default
# ``gaussian``, ``tent``) splats each sample over its neighbours, the noise becomes spatially
# correlated, and OIDN leaves it in place: on Mitsuba's Cornell box at 4 spp OIDN gains +10.8 dB
# on a box-filtered render and +0.1 dB on a Gaussian-filtered one (docs/diffusion.md).
#
# ``neighbour_ratio`` measures it without a reference. A second difference (x[i-k] - 2 x[i] + x[i+k])
# cancels any linear trend of the image; over independent noise it has the same spread at k = 1 and
# k = 2, while correlated noise makes neighbours alike and shrinks the k = 1 one. The spreads are
# medians of absolute second differences of log(1 + luminance) along rows and columns, robust to
# edges and fireflies. Measured on Mitsuba's Cornell box (96², with and without a glass sphere), at
# 1-256 spp: 0.82-0.93 with a box filter, 0.56-0.65 with ``gaussian``, 0.62-0.72 with ``tent``. A nearly
# noise-free image reads low whatever the filter (at 4096 spp the box filter reads 0.69-0.75): there
# the signal's own curvature dominates, and there is little noise left to remove anyway.
CORRELATED_BELOW = 0.77   # box filter at 1-256 spp: >= 0.82; gaussian and tent: <= 0.72


def _log_luminance(color: np.ndarray) -> np.ndarray:
    return np.log1p(np.maximum(np.nan_to_num(np.asarray(color, np.float64)), 0).mean(-1))


def _second_differences(y: np.ndarray, k: int) -> np.ndarray:
    rows = y[:, 2 * k:] - 2 * y[:, k:-k] + y[:, :-2 * k]
    cols = y[2 * k:] - 2 * y[k:-k] + y[:-2 * k]
    return np.concatenate([rows.ravel(), cols.ravel()])


def neighbour_ratio(color: np.ndarray) -> float | None:
    """Median |second difference at lag 1| over median |second difference at lag 2| of log(1 + luminance),
    rows and columns pooled; None when the image is too small or flat to tell."""
    y = _log_luminance(color)
    if min(y.shape) < 5:
        return None
    lag2 = float(np.median(np.abs(_second_differences(y, 2))))
    return float(np.median(np.abs(_second_differences(y, 1)))) / lag2 if lag2 > 0 else None


def correlated_noise(color: np.ndarray) -> float | None:
    """The ratio when it says the noise is spatially correlated (below ``CORRELATED_BELOW``), else None."""
    r = neighbour_ratio(color)
    return r if r is not None and r < CORRELATED_BELOW else None
