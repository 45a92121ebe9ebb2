"""Inference: denoise a frame with a trained model folder (a run or ``train/shipped``), and σ's calibration.

    den = load_denoiser(find_run(cfg, 4))                  # or base_only=True: the ablation row
    hdr = den.denoise(store.read(scene, frame, 4), spp=4, seed=0)          # (H, W, 3) float32
    hdr, std = den.denoise(buffers, spp=4, samples=8, with_std=True)       # mean of 8 and their std

What the model cannot represent is said, not hidden: non-finite input values are replaced by 0
(``last_repaired``), an all-black input is returned black (``last_black``), an input without albedo
and normal gets OIDN on what there is (``last_estimate_only``), pixels past OIDN's output range are
clamped (``last_clamped``).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from mcdenoise.pipeline import oidn_net, oidn_weights
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.numerics import repair_nonfinite, shorten_normals
from mcdenoise.pipeline.runs import pick_device

from .data import inputs, present
from .formulation import Formulation
from .model import ControlledOIDN, clean_aux, load, oidn_ft_blob
from .sampler import check_strength, sample, with_strength

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
                strength: float | None = None):
        """HDR (H, W, 3) float32 (and the per-pixel std of ``samples`` samples with ``with_std``);
        ``strength``: the fraction of the Control Module's change applied (default: the model's)."""
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
        from mcdenoise.pipeline import oidn
        network = oidn_weights.network_for("albedo" in buffers, False)
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
                                aux_device=None if self.device.type == "cpu" else str(self.device))
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
        hdr = oidn_net.network_output(mean, scale, (H, W))
        slope = (oidn_net.network_output(mean + 1e-4, scale, (H, W)) - hdr) / 1e-4
        as_image = lambda t: np.ascontiguousarray(t[0].permute(1, 2, 0).float().cpu().numpy())  # noqa: E731
        return as_image(hdr), as_image(slope.abs() * std[..., :H, :W])


def load_denoiser(folder: str | Path, device: str = "auto", base_only: bool = False, precision: str = "auto") -> Denoiser:
    dev = pick_device(device)
    model, meta = load(folder, dev)
    return Denoiser(model, meta, dev, base_only, Path(folder), precision)
