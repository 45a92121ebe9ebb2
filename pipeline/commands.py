"""The core's part of the command line: the options every stage's subcommands share and the core's own
subcommands (``inspect``, ``config``, ``verify``).

Each package declares its subcommands in its ``commands`` module with ``add_commands(subparsers)``
(name, help, flags, and the handler ``fn(args) -> exit status`` bound with ``set_defaults``);
``pipeline.__main__`` builds the parser from them and dispatches. A ``commands`` module loads
nothing heavy (no torch, numpy or Mitsuba) at import: every command's parser is built on every call,
so a handler imports what its command runs.
"""
from __future__ import annotations

import argparse
import json

from .config import Config, documentation_markdown, load_config, to_dict


def with_config(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the arguments of every subcommand that reads the config: --config FILE and key=value overrides."""
    p.add_argument("--config", default=None, help="YAML config (default: built-in defaults)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="override config keys")
    return p


def with_defines(p):
    """``-D NAME=VALUE`` (repeatable): the Mitsuba scene parameters ``$NAME`` of the XML scenes given."""
    p.add_argument("-D", dest="defines", action="append", default=None, metavar="NAME=VALUE",
                   help="a value for the scene parameter $NAME of the XML (as Mitsuba's -D); repeat for several")
    return p


def with_quiet(p: argparse.ArgumentParser, text: str | None = None) -> argparse.ArgumentParser:
    """Add --quiet, the flag of every subcommand that reports progress (``text``: its help, if any)."""
    p.add_argument("--quiet", action="store_true", help=text)
    return p


def config(args: argparse.Namespace) -> Config:
    """The config a subcommand of ``with_config`` was given."""
    return load_config(args.config, args.overrides)


def spp(text: str) -> int | str:
    """``--spp``'s type where 'any' (one model for every sample count) is allowed."""
    if text == "any":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a sample count (4, 16, 64) or 'any', got {text!r}") from None


def add_commands(sub) -> None:
    """The core's subcommands: store tools and the config."""
    p = sub.add_parser("inspect", help="describe a store (frames, channels, constants, timings, NaN/Inf)")
    p.add_argument("store")
    p.add_argument("--frame", default=None, help="SCENE/FRAME, e.g. s00000/000: details of one frame")
    p.add_argument("--json", action="store_true")
    p.set_defaults(fn=_inspect)

    p = with_config(sub.add_parser("config", help="print the resolved config, or --doc the key reference"))
    p.add_argument("--doc", action="store_true")
    p.set_defaults(fn=_config)

    p = sub.add_parser("verify", help="check every file of a store (readable, channels, shapes, checksums, "
                                      "manifests, gt_clean hashes, leftover .tmp); exit 1 on any problem")
    p.add_argument("store")
    p.add_argument("--headers-only", action="store_true", help="skip pixel data and checksums (fast)")
    p.add_argument("--jobs", type=int, default=1, help="check scenes in this many processes")
    with_quiet(p, "only the summary line")
    p.add_argument("--bytes", type=int, default=0, metavar="N",
                   help="instead of checking: bytes per channel group of N frames, as stored and re-encoded compact")
    p.add_argument("--encodings", type=int, default=0, metavar="N",
                   help="instead of checking: bytes, write and read seconds per frame of each encoding on N frames")
    p.set_defaults(fn=_verify)


def _inspect(args) -> int:
    from .inspect import format_report, inspect_store
    report = inspect_store(args.store, frame=args.frame)
    print(json.dumps(report, indent=1, sort_keys=True) if args.json else format_report(report))
    return 0


def _config(args) -> int:
    if args.doc:
        print(documentation_markdown(), end="")
        return 0
    import yaml
    print(yaml.safe_dump(to_dict(config(args)), sort_keys=False), end="")
    return 0


def _verify(args) -> int:
    from .verify import bytes_table, encodings_table, measure_bytes, measure_encodings, run_verify
    if args.encodings:
        print(encodings_table(measure_encodings(args.store, args.encodings)))
        return 0
    if args.bytes:
        print(bytes_table(measure_bytes(args.store, args.bytes)))
        return 0
    return run_verify(args.store, quiet=args.quiet, pixels=not args.headers_only, jobs=args.jobs)
