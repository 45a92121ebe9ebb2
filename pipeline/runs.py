"""Training runs: the folder each model writes under ``cfg.runs``, and the device it runs on.

One folder per model and sample count (``spp<N>``, or ``sppany`` for one model serving every count):

- ``cleaner``: ``<runs>/cleaner``;
- ``isik`` (the Isik baseline): ``<runs>/isik_spp<N>``;
- ``afgsa``: ``<runs>/afgsa_spp<N>``; trained against another target than gt_clean
  (``afgsa.target``): ``<runs>/afgsa_<target>_spp<N>``;
- ``oidn_ft`` (OIDN fine-tuned, one model for every spp): ``<runs>/oidn_ft_<network>``
  (``oidn_ft.network``, or the network given as ``variant``);
- ``diffusion``: ``<runs>/diffusion_spp<N>``, with ``_<variant>`` (``diffusion.name``, or the
  variant given) appended.

``find_run``: the run that serves a sample count, its own (``spp<N>``) else the one for every
count (``sppany``); the evaluator, ``denoise`` and the reports find Isik, AFGSA and diffusion runs by it.

Importing this module does not import torch; ``pick_device`` does.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from .config import Config

MODELS = ("cleaner", "isik", "afgsa", "oidn_ft", "diffusion")


def spp_tag(spp: int | str) -> str:
    """``spp4``, ``spp16``, ..., or ``sppany``."""
    return "sppany" if str(spp) == "any" else f"spp{int(spp)}"


def run_dir(cfg: Config, model: str, spp: int | str | None = None, variant: str | None = None) -> Path:
    """The run folder of ``model`` (one of ``MODELS``) at ``spp``; ``variant``: for diffusion the run
    variant (default: ``diffusion.name``), for oidn_ft the network (default: ``oidn_ft.network``)."""
    runs = Path(cfg.runs)
    if model == "cleaner":
        return runs / "cleaner"
    if model == "isik":
        return runs / f"isik_{spp_tag(spp)}"
    if model == "afgsa":
        target = "" if cfg.afgsa.target == "gt_clean" else f"_{cfg.afgsa.target}"
        return runs / f"afgsa{target}_{spp_tag(spp)}"
    if model == "oidn_ft":
        return runs / f"oidn_ft_{variant or cfg.oidn_ft.network}"
    if model == "diffusion":
        variant = cfg.diffusion.name if variant is None else variant
        return runs / (f"diffusion_{spp_tag(spp)}" + (f"_{variant}" if variant else ""))
    raise ValueError(f"model must be one of {', '.join(MODELS)}, got {model!r}")


def run_candidates(cfg: Config, model: str, spp: int | str, variant: str | None = None) -> list[Path]:
    """Where the run of ``model`` that serves ``spp`` may be, in order: its own (``<model>_spp<N>``), then
    the one model for every sample count (``<model>_sppany``); for ``spp`` 'any' only that one."""
    own = run_dir(cfg, model, spp, variant)
    return [own] if str(spp) == "any" else [own, run_dir(cfg, model, "any", variant)]


def find_run(cfg: Config, model: str, spp: int | str, weights: str, variant: str | None = None,
             serves: Callable[[Path], bool] | None = None, fallback: Path | None = None) -> Path | None:
    """The run of ``model`` that serves ``spp``: the first of ``run_candidates`` with ``weights`` (a file name)
    in it, the any-spp run only where ``serves(folder)`` says it trained on ``spp`` (default: it serves
    every count), else ``fallback`` when it has ``weights``; None if none does."""
    own, *others = run_candidates(cfg, model, spp, variant)
    if (own / weights).exists():
        return own
    for folder in others:
        if (folder / weights).exists() and (serves is None or serves(folder)):
            return folder
    if fallback is not None and (fallback / weights).exists():
        return fallback
    return None


def pick_device(name: str):
    """The torch device of a ``*.device`` config key: 'auto' is CUDA where available, else the CPU."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)
