"""Training runs: the folder each model writes under ``cfg.runs``, and the device it runs on.

One folder per model and sample count (``spp<N>``, or ``sppany`` for one model serving every count):

- ``cleaner``: ``<runs>/cleaner``;
- ``isik`` (the Isik baseline): ``<runs>/isik_spp<N>``;
- ``afgsa``: ``<runs>/afgsa_spp<N>``; trained against another target than gt_clean
  (``afgsa.target``): ``<runs>/afgsa_<target>_spp<N>``;
- ``base`` (the stand-in diffusion base of ``make pretrain``): ``<runs>/base`` (or ``pretrain.out``);
- ``oidn_ft`` (OIDN fine-tuned, one model for every spp): ``<runs>/oidn_ft_<network>``
  (``oidn_ft.network``, or the network given as ``variant``);
- ``diffusion``: ``<runs>/diffusion_spp<N>``, with ``_<variant>`` (``diffusion.name``, or the
  variant given) and ``_base_only`` (``diffusion.control`` false) appended.

Importing this module does not import torch; ``pick_device`` does.
"""
from __future__ import annotations

from pathlib import Path

from .config import Config

MODELS = ("cleaner", "isik", "afgsa", "base", "oidn_ft", "diffusion")


def spp_tag(spp: int | str) -> str:
    """``spp4``, ``spp16``, ..., or ``sppany``."""
    return "sppany" if str(spp) == "any" else f"spp{int(spp)}"


def run_dir(cfg: Config, model: str, spp: int | str | None = None, variant: str | None = None) -> Path:
    """The run folder of ``model`` (one of ``MODELS``) at ``spp``; ``variant``: for diffusion the run
    variant (default: ``diffusion.name``), for oidn_ft the network (default: ``oidn_ft.network``)."""
    runs = Path(cfg.runs)
    if model == "cleaner":
        return runs / "cleaner"
    if model == "base":
        return Path(cfg.pretrain.out) if cfg.pretrain.out else runs / "base"
    if model == "isik":
        return runs / f"isik_{spp_tag(spp)}"
    if model == "afgsa":
        target = "" if cfg.afgsa.target == "gt_clean" else f"_{cfg.afgsa.target}"
        return runs / f"afgsa{target}_{spp_tag(spp)}"
    if model == "oidn_ft":
        return runs / f"oidn_ft_{variant or cfg.oidn_ft.network}"
    if model == "diffusion":
        variant = cfg.diffusion.name if variant is None else variant
        name = f"diffusion_{spp_tag(spp)}" + (f"_{variant}" if variant else "")
        return runs / (name if cfg.diffusion.control else name + "_base_only")
    raise ValueError(f"model must be one of {', '.join(MODELS)}, got {model!r}")


def pick_device(name: str):
    """The torch device of a ``*.device`` config key: 'auto' is CUDA where available, else the CPU."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)
