"""The methods the evaluator compares, each behind one small interface.

A ``Method`` has a ``name``, a ``device`` and ``denoise(buffers) -> (H, W, 3) float32 HDR``,
where ``buffers`` is what ``Store.read(scene, frame, spp)`` returns (buffer name → (H, W, C)
array, variances included). One instance serves one sample count (the Isik baseline and the
diffusion model are trained per spp). Timing, input repair and output checks are done by the
harness (``evaluate.harness.run_method``), never by a method.

Names (``eval.methods``):

- ``noisy``: the input colour itself.
- ``oidn``: Intel Open Image Denoise 2.5 (``pyoidn``), filter RT in HDR mode, quality high, with
  albedo and normal (noisy auxiliaries, so OIDN prefilters them: ``cleanAux`` off). ``oidn_color``:
  colour only. OIDN takes world- or view-space normals in [-1, 1] (need not be normalised) and
  albedo in [0, 1]: ours are world space, clamped to those ranges before the call.
- ``isik``: the affinity-network baseline of ``runs/<...>/isik_spp<N>`` (``make train MODEL=isik``).
- ``afgsa``: AFGSA (Yu et al. 2021, ``clean.afgsa``) of ``runs/<...>/afgsa_spp<N>``, else of the
  all-spp run ``afgsa_sppany`` (``make train MODEL=afgsa SPP=N|any``); both run through
  ``clean.apply.denoise`` (tiled).
- ``ours``, ``ours_skipN``: the diffusion denoiser of ``train.infer`` at all 27 super27 steps or
  with N of them skipped; ``base_only``, ``base_only_skipN``: the same base without its Control
  Module (the paper's ablation row). ``ours_small[_skipN]``, ``base_only_small[_skipN]``: the
  same with the sampler's fixed posterior variance instead of the learned one (``variance="small"``:
  a weakly trained network predicts a large variance, which its samples then carry as noise).
  These are looked up lazily, as

      from train.infer import load_denoiser, run_dir
      den = load_denoiser(run_dir(cfg, spp), device=device, base_only=False)
      hdr = den.denoise(buffers, spp=spp, skip=N, seed=cfg.eval.seed)

  A missing module or checkpoint makes the method *not available* with the reason (a row in the
  table), never a crash and never made-up numbers.
"""
from __future__ import annotations

import re
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.config import Config, ConfigError
from pipeline.exr import StoreError

# Diffusion families: (without the Control Module, sampler variance). They take a _skipN suffix.
_DIFFUSION = {"ours": (False, "learned"), "base_only": (True, "learned"),
              "ours_small": (False, "small"), "base_only_small": (True, "small")}
FAMILIES = ("noisy", "oidn", "oidn_color", "isik", "afgsa", *_DIFFUSION)
_NAME = re.compile(r"^(?P<family>[a-z_]+?)(?:_skip(?P<skip>\d+))?$")
LABELS = {"noisy": "Noisy input", "oidn": "OIDN (colour+albedo+normal)", "oidn_color": "OIDN (colour only)",
          "isik": "Isik et al.", "afgsa": "AFGSA (Yu et al. 2021)", "ours": "Ours (diffusion)",
          "base_only": "Base only (no Control Module)",
          "ours_small": "Ours (diffusion), fixed small variance",
          "base_only_small": "Base only (no Control Module), fixed small variance"}


class MethodUnavailable(Exception):
    """The method cannot run here (missing package, module or checkpoint); the message says why."""


def parse_name(name: str) -> tuple[str, int]:
    """``ours_skip12`` → ("ours", 12); ``oidn_color`` → ("oidn_color", 0). Unknown names: ConfigError."""
    m = _NAME.match(name)
    family, skip = (m.group("family"), int(m.group("skip") or 0)) if m else (name, 0)
    if m and m.group("skip") is not None and family not in _DIFFUSION:
        family = None
    if family not in FAMILIES:
        raise ConfigError(f"eval.methods: unknown method {name!r} (known: {', '.join(FAMILIES)}, "
                          f"and <ours|base_only>[_small]_skipN)")
    return family, skip


def label(name: str) -> str:
    family, skip = parse_name(name)
    return LABELS[family] + (f", {skip} of 27 steps skipped" if skip else "")


class Method(ABC):
    """One denoiser at one sample count."""

    name: str = ""
    device: str = "cpu"

    @abstractmethod
    def denoise(self, buffers: dict[str, np.ndarray]) -> np.ndarray:
        """HDR radiance (H, W, 3) float32 from one frame's buffers."""

    def set_frame(self, store, key) -> None:
        """Called before ``denoise`` with the frame's store and key, for methods that need more than
        its buffers (the diffusion model reads the camera to put normals in camera space)."""


@dataclass
class Noisy(Method):
    name: str = "noisy"
    device: str = "-"

    def denoise(self, buffers):
        return np.array(buffers["color"], dtype=np.float32)


@dataclass
class OIDN(Method):
    name: str = "oidn"
    aux: bool = True
    quality: str = "high"
    device: str = "cpu"

    def __post_init__(self):
        try:
            import pyoidn  # noqa: F401
        except ImportError as exc:
            raise MethodUnavailable(f"pyoidn is not installed ({exc}); pip install pyoidn==2.5.1.0") from None

    def denoise(self, buffers):
        import pyoidn

        color = np.ascontiguousarray(np.maximum(buffers["color"], 0), dtype=np.float32)
        albedo = normal = None
        if self.aux:
            albedo = np.ascontiguousarray(np.clip(buffers["albedo"], 0, 1), dtype=np.float32)
            normal = np.ascontiguousarray(np.clip(buffers["normal"], -1, 1), dtype=np.float32)
        return pyoidn.denoise(color, albedo, normal, hdr=True, quality=self.quality)


@dataclass
class CleanNet(Method):
    """A network of ``clean`` (the Isik baseline, AFGSA) on ``frame_inputs``, tiled by ``clean.apply``."""

    model: object = None
    tile: int = 512
    name: str = "isik"
    device: str = "cpu"

    def denoise(self, buffers):
        from clean.apply import denoise
        from clean.data import frame_inputs

        inputs, radiance = frame_inputs(buffers)
        return denoise(self.model, inputs, radiance, tile=self.tile, device=self.device)


@dataclass
class Diffusion(Method):
    """``ours``/``base_only`` through ``train.infer``'s denoiser object."""

    denoiser: object = None
    spp: int = 4
    skip: int = 0
    seed: int = 0
    name: str = "ours"
    device: str = "cpu"

    rotation: object = None
    variance: str = "learned"

    def set_frame(self, store, key) -> None:
        from train.data import frame_rotation
        self.rotation = frame_rotation(store, key)

    def denoise(self, buffers):
        out = self.denoiser.denoise(buffers, spp=self.spp, skip=self.skip, seed=self.seed, rotation=self.rotation,
                                    variance=self.variance)
        return np.asarray(out, dtype=np.float32)


@dataclass
class Loader:
    """Builds methods for one config; loaded models are shared (ours and ours_skipN use one model)."""

    cfg: Config
    _models: dict = field(default_factory=dict)

    def device(self) -> str:
        from clean.train import pick_device
        return str(pick_device(self.cfg.eval.device))

    def load(self, name: str, spp: int) -> Method:
        """The method ``name`` at ``spp``; raises ``MethodUnavailable`` with the reason."""
        family, skip = parse_name(name)
        if family == "noisy":
            return Noisy()
        if family in ("oidn", "oidn_color"):
            return OIDN(name=name, aux=family == "oidn")
        if family in ("isik", "afgsa"):
            return self._clean_net(family, spp)
        return self._diffusion(name, family, skip, spp)

    def _clean_net(self, family: str, spp: int) -> Method:
        from clean.model import load_model
        from clean.train import run_dir

        mode, section = ("baseline", self.cfg.clean) if family == "isik" else ("afgsa", self.cfg.afgsa)
        folders = [run_dir(self.cfg, mode, spp)] + ([run_dir(self.cfg, mode, "any")] if family == "afgsa" else [])
        folder = next((f for f in folders if (f / "model.safetensors").exists()), None)
        if folder is None:
            raise MethodUnavailable(f"no {'Isik' if family == 'isik' else 'AFGSA'} checkpoint in "
                                    f"{' or '.join(map(str, folders))}: run `make train MODEL={family} SPP={spp}`")
        if folder not in self._models:
            self._models[folder] = load_model(folder, self.device())[0]
        return CleanNet(model=self._models[folder], tile=section.tile, name=family, device=self.device())

    def _diffusion(self, name: str, family: str, skip: int, spp: int) -> Method:
        base_only, variance = _DIFFUSION[family]
        key = ("diffusion", spp, base_only)
        if key not in self._models:
            try:
                from train.infer import load_denoiser, run_dir
            except ImportError as exc:
                raise MethodUnavailable(f"the diffusion model is not built yet (import train.infer: {exc}); "
                                        f"run `make train SPP={spp}` once it is") from None
            folder = Path(run_dir(self.cfg, spp))
            if not base_only and not folder.exists():
                raise MethodUnavailable(f"no diffusion checkpoint in {folder}: run `make train "
                                        f"SPP={spp}`")
            try:
                self._models[key] = load_denoiser(folder, device=self.device(), base_only=base_only)
            except (OSError, StoreError, ConfigError, ValueError, KeyError) as exc:
                raise MethodUnavailable(f"cannot load the diffusion model from {folder}: "
                                        f"{type(exc).__name__}: {exc}") from None
        if not 0 <= skip < 27:
            raise MethodUnavailable(f"{name}: skip must be 0..26 of the 27 super27 steps")
        return Diffusion(denoiser=self._models[key], spp=spp, skip=skip, seed=self.cfg.eval.seed, name=name,
                         device=self.device(), variance=variance)


def check_names(names: list[str]) -> None:
    for name in names:
        parse_name(name)
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"eval.methods: {', '.join(dup)} listed twice")
