"""Assemble the controlled denoiser from a config, and save / load a trained run.

A run folder (``runs/<name>/diffusion_spp{N}``, ``diffusion_sppany``) holds:

- ``control.safetensors``: the Control Module's weights (and ``base.*`` when the base trained
  too), the best epoch by validation PSNR;
- ``model.json``: what is needed to rebuild it: the base folder and the SHA-256 of its weights
  (a changed base is refused: the Control Module only fits the base it was trained with), the
  condition's channel names, the tonemap, the spp, the sampler defaults, the metrics;
- ``last.safetensors``: the resumable state (``pipeline.checkpoint``), ``loss.png``, ``train.json``.
"""
from __future__ import annotations

from pathlib import Path

import torch

from mcdenoise.pipeline import runs, weights
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.errors import CheckpointError, StoreError, TrainError
from mcdenoise.pipeline.store import sha256

from . import base as base_lib
from .control import ControlledDenoiser, ControlModule
from .data import aux_names
from .estimate import KINDS, Estimator, load as load_estimator
from .formulation import Formulation
from .sampler import PAPER

FORMAT = weights.FORMATS["control"]
# The denoiser shipped with the repository (base + Control Module + model card), used when a config
# has no trained run of its own (train/shipped/README.md says how it was made).
SHIPPED_MODEL = Path(__file__).resolve().parent / "shipped"


def base_folder(cfg: Config, run: Path | None = None) -> Path:
    """``diffusion.base``; empty: the paper formulation's shipped stand-in (train/base_model_paper), or for
    the refine formulation a new base with a zero last layer in the run folder (``base_init``, written
    by ``new_base``: training starts exactly at the first estimate)."""
    if cfg.diffusion.base:
        return Path(cfg.diffusion.base)
    if Formulation.from_config(cfg.diffusion).paper:
        return base_lib.PAPER_BASE
    return Path(run if run is not None else run_dir(cfg, "any")) / "base_init"


def new_base(cfg: Config, run: Path) -> None:
    """Write the run's new base (``base_folder``) if the config asks for one and it is not there yet."""
    folder = base_folder(cfg, run)
    if cfg.diffusion.base or Formulation.from_config(cfg.diffusion).paper or (folder / base_lib.WEIGHTS).exists():
        return
    if not cfg.diffusion.train_base:
        raise StoreError("a new base (diffusion.base empty) starts with a zero last layer and must train with the "
                         "Control Module: set diffusion.train_base=true, or pretrain one (make pretrain) and set "
                         "diffusion.base to it")
    base_lib.write_new(folder, cfg.pretrain.channels, cfg.pretrain.layers_per_block, cfg.seed)


def run_dir(cfg: Config, spp: int | str, variant: str | None = None) -> Path:
    """``diffusion_spp4``, ``diffusion_sppany``, ``diffusion_sppany_paper`` (variant ``paper``) under
    ``cfg.runs``, ``_base_only`` appended without the Control Module (``pipeline.runs.run_dir``)."""
    return runs.run_dir(cfg, "diffusion", spp, variant)


def oidn_ft_blob(folder: Path, network: str) -> Path:
    """Where a model folder (``train/shipped``, an export) keeps OIDN's ``network`` fine-tuned, the weights
    it runs on inputs without the layers its base reads; the folder may not have them."""
    return Path(folder) / "oidn_ft" / f"{network}.tza"


def find_run(cfg: Config, spp: int | str, variant: str | None = None) -> Path:
    """The trained run for ``spp``: ``diffusion_spp<N>[_variant]`` if it exists, else the spp-conditioned
    ``diffusion_sppany[_variant]`` (one model serves every sample count), else (no variant, and
    ``diffusion.shipped``) the model shipped with the repository (``SHIPPED_MODEL``); CheckpointError (a StoreError) if none."""
    named = variant if variant is not None else cfg.diffusion.name
    shipped = SHIPPED_MODEL if not named and cfg.diffusion.shipped and cfg.diffusion.control else None
    folder = runs.find_run(cfg, "diffusion", spp, "model.json", variant, fallback=shipped)
    if folder is not None:
        return folder
    candidates = runs.run_candidates(cfg, "diffusion", spp, variant) + ([shipped] if shipped else [])
    raise CheckpointError(f"no diffusion checkpoint in {' or '.join(map(str, candidates))}: run "
                          f"`make train SPP={spp}` or `make train SPP=any`" +
                          (f" with diffusion.name={variant}" if variant else ""))


def isik_folder(cfg: Config) -> Path:
    """The Isik network a first estimate with ``isik`` uses: ``diffusion.isik_run``, else <runs>/isik_sppany."""
    return Path(cfg.diffusion.isik_run) if cfg.diffusion.isik_run else Path(cfg.runs) / "isik_sppany"


def estimator(cfg: Config, device="cpu") -> Estimator:
    return load_estimator(Formulation.from_config(cfg.diffusion).estimate, isik_folder(cfg), device)


def estimator_and_id(cfg: Config) -> tuple[Estimator, str]:
    """(the configured first estimate, an id of its weights for a pack's header: the Isik network's SHA-256)."""
    est = estimator(cfg)
    return est, sha256(isik_folder(cfg) / "model.safetensors") if est.isik is not None else ""


def base_sha256(cfg: Config, run: Path) -> str:
    """The SHA-256 of the weights of the run's base (``base_folder``); a clear error when they are missing."""
    path = base_folder(cfg, run) / base_lib.WEIGHTS
    if not path.exists():
        raise TrainError(f"{path}: base weights missing; run `make pretrain` or set diffusion.base")
    return sha256(path)


def build(cfg: Config, seed: int | None = None, run: Path | None = None) -> ControlledDenoiser:
    """The base (``base_folder``) plus a fresh Control Module (or none, ``control: false``)."""
    unet, prompt = base_lib.load(base_folder(cfg, run))
    torch.manual_seed(cfg.seed if seed is None else seed)
    aux = len(aux_names(Formulation.from_config(cfg.diffusion).estimate))
    control = ControlModule(unet, aux) if cfg.diffusion.control else None
    return ControlledDenoiser(unet, prompt, control, train_base=cfg.diffusion.train_base)


def trainable_state(model: ControlledDenoiser) -> dict[str, torch.Tensor]:
    state = {}
    if model.control is not None:
        state.update({f"control.{k}": v for k, v in model.control.state_dict().items()})
    if model.train_base:
        state.update({f"base.{k}": v for k, v in model.base.state_dict().items()})
    return state


def save(folder: Path, model: ControlledDenoiser, cfg: Config, spp, record: dict) -> None:
    base = base_folder(cfg, folder)
    form = Formulation.from_config(cfg.diffusion)
    isik = {}
    if "isik" in KINDS[form.estimate]:
        isik = {"isik": str(isik_folder(cfg).resolve()), "isik_sha256": sha256(isik_folder(cfg) / "model.safetensors")}
    weights.save(folder, "control", trainable_state(model), {
        "spp": spp, "base": str(base.resolve()),
        "base_sha256": sha256(base / base_lib.WEIGHTS), "aux_channels": aux_names(form.estimate), **isik,
        "control": model.control is not None, "train_base": model.train_base,
        "tonemap": cfg.diffusion.tonemap, "skip": cfg.diffusion.skip,
        "threshold_ratio": cfg.diffusion.threshold_ratio, "variance": cfg.diffusion.variance,
        "formulation": Formulation.from_config(cfg.diffusion).record(), **record}, weights="control.safetensors")


def _checked(folder: Path, meta: dict, key: str, file: str) -> Path:
    """The folder ``meta[key]`` names (relative to ``folder`` for shipped runs), its weights unchanged."""
    where = Path(meta[key])
    where = where if where.is_absolute() else (folder / where).resolve()
    if not (where / file).exists():
        raise CheckpointError(f"{folder / 'model.json'}: its {key} {where} is missing; retrain, or restore that folder")
    weights.check_sha256(where / file, meta[f"{key}_sha256"], f"{where / file}: the {key} of {folder}",
                         "retrain the Control Module for it")
    return where


def load_run_estimator(folder: str | Path, meta: dict, device="cpu") -> Estimator:
    """The first estimate a run was trained with (its Isik network checked like its base)."""
    kind = formulation(meta).estimate
    isik = _checked(Path(folder), meta, "isik", "model.safetensors") if "isik" in KINDS[kind] else None
    return load_estimator(kind, isik, device)


def formulation(meta: dict) -> Formulation:
    """The formulation a run was trained with (records older than the refine formulation: the paper's)."""
    rec = meta.get("formulation")
    return Formulation.from_record(rec) if rec else PAPER


def load(folder: str | Path, device: str | torch.device = "cpu") -> tuple[ControlledDenoiser, dict]:
    """(model in eval mode, model.json) of a trained run; refuses a changed base or channel layout."""
    folder = Path(folder)
    meta_path = folder / "model.json"
    meta = weights.read_record(folder, "control", "run `make train SPP=<n>`")
    names = aux_names(formulation(meta).estimate)
    if meta.get("aux_channels") != names:
        raise CheckpointError(f"{meta_path}: trained on another condition layout ({len(meta.get('aux_channels', []))} "
                              f"channels, this code makes {len(names)}); retrain")
    base = _checked(folder, meta, "base", base_lib.WEIGHTS)
    unet, prompt = base_lib.load(base)
    control = ControlModule(unet, len(names)) if meta["control"] else None
    model = ControlledDenoiser(unet, prompt, control, train_base=False)
    state = weights.load_tensors(folder / "control.safetensors")
    if control is not None:
        control.load_state_dict({k[8:]: v for k, v in state.items() if k.startswith("control.")})
    if meta.get("train_base"):
        unet.load_state_dict({k[5:]: v for k, v in state.items() if k.startswith("base.")})
    return model.to(device).eval(), meta
