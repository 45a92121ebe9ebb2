"""Command-line entry points of the cleaner stage, called by ``python -m pipeline``.

    python -m pipeline gt-clean [--config FILE] [key=value ...]       → cmd_gt_clean(cfg)
    python -m pipeline train --model isik --spp 4|any [--config FILE] ... → cmd_train_isik(cfg, 4)

All return a process exit status. Training resumes from the run folder's last checkpoint and is
a no-op when it already reached ``clean.epochs``; applying is a no-op for frames whose
gt_clean.exr was made by the current checkpoint, so rerunning ``make gt-clean`` is cheap.
"""
from __future__ import annotations

from mcdenoise.pipeline.config import Config


def cmd_gt_clean(cfg: Config, quiet: bool = False) -> int:
    """Train the cleaner if needed (or resume it), then write GT_clean for every frame."""
    from .apply import apply_cleaner
    from .train import train

    train(cfg, mode="cleaner", quiet=quiet)
    stats = apply_cleaner(cfg, quiet=quiet)
    return 0 if stats["written"] + stats["skipped"] > 0 else 1


def cmd_train_isik(cfg: Config, spp: int | str, quiet: bool = False) -> int:
    """Train the Isik baseline from the ``spp`` low-spp buffers to GT_clean ('any': one model for
    every sample count the stacks pool, which the evaluator uses where no per-spp run exists)."""
    from .train import train

    train(cfg, mode="baseline", spp=spp if str(spp) == "any" else int(spp), quiet=quiet)
    return 0
