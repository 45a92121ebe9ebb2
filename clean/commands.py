"""The cleaner stage's subcommands of ``python -m pipeline``: ``gt-clean`` and ``clean-report``.

``add_commands`` declares them (see ``pipeline.commands``); each handler imports what it runs. The
Isik baseline trains through ``train --model isik`` (``train.commands``, calling ``clean.cli``).
"""
from __future__ import annotations

from mcdenoise.pipeline.commands import config, with_config, with_quiet


def add_commands(sub) -> None:
    """``gt-clean`` and ``clean-report``."""
    p = with_config(sub.add_parser("gt-clean", help="train the GT cleaner (resumable), then write gt_clean for every frame"))
    with_quiet(p)
    p.set_defaults(fn=_gt_clean)

    p = with_config(sub.add_parser("clean-report", help="GT1 vs GT_clean against GT2 on val/test, crop grid; "
                                                         "--spp N adds the Isik baseline on the test split"))
    p.add_argument("--out", default="reports/cleaner")
    p.add_argument("--spp", type=int, default=None)
    p.set_defaults(fn=_clean_report)


def _gt_clean(args) -> int:
    from .cli import cmd_gt_clean
    return cmd_gt_clean(config(args), quiet=args.quiet)


def _clean_report(args) -> int:
    from .report import run_report
    run_report(config(args), out=args.out, spp=args.spp)
    return 0
