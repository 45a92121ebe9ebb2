"""The evaluation stage's subcommands of ``python -m pipeline``: ``eval`` and ``stability``.

``add_commands`` declares them (see ``pipeline.commands``); each handler imports what it runs.
"""
from __future__ import annotations

from mcdenoise.pipeline.commands import config, with_config, with_defines, with_quiet
from mcdenoise.pipeline.config import ConfigError


def add_commands(sub) -> None:
    """``eval`` and ``stability``."""
    p = with_config(sub.add_parser("eval", help="every method on the test frames per spp: tables, error vs time, "
                                                "crops (reports/<run>/)"))
    p.add_argument("--spp", default=None, help="sample counts, comma-separated, e.g. 4 or 4,16 (default: eval.spp)")
    p.add_argument("--scene", action="append", default=None, metavar="XML", dest="scenes",
                   help="a Mitsuba 3 scene to render into the store (split 'external') and report separately; "
                        "repeat for several")
    with_defines(p)
    p.add_argument("--out", default=None, help="report folder (default: eval.out or reports/<runs name>)")
    with_quiet(p)
    p.set_defaults(fn=_eval)

    p = with_config(sub.add_parser("stability", help="every method on synthetic edge cases (fireflies, NaN, sizes, ...)"))
    p.add_argument("--out", default=None, help="report folder (default: as eval)")
    with_quiet(p)
    p.set_defaults(fn=_stability)


def _eval(args) -> int:
    from mcdenoise.render.external import parse_defines

    from .run import run_eval
    spps = None
    if args.spp:
        try:
            spps = [int(v) for v in args.spp.split(",") if v.strip()]
        except ValueError:
            raise ConfigError(f"--spp {args.spp!r}: expected sample counts such as 4 or 4,16,64") from None
    if args.defines and not args.scenes:
        raise ConfigError("-D sets parameters of the XML scenes given with --scene; no --scene was given")
    run_eval(config(args), spps=spps, scenes=args.scenes, out=args.out, quiet=args.quiet,
             defines=parse_defines(args.defines))
    return 0


def _stability(args) -> int:
    from .stability import run_stability
    data = run_stability(config(args), out=args.out, quiet=args.quiet)
    failed = sum(c["status"] not in ("ok", "not available") for r in data["results"].values() for c in r.values())
    return 1 if failed else 0
