"""Command line: ``python -m pipeline <stage> [--config FILE] [key=value ...]``.

Every stage reads the same typed config (``pipeline.config``); ``key=value`` overrides any key
(dotted for sections: ``dataset.scenes=4``). Errors in input (config, store, scene files,
checkpoints: every ``pipeline.errors.PipelineError``) print one line naming the culprit and exit
with status 2; nothing half-written is left behind.
"""
from __future__ import annotations

import argparse
import errno
import os
import re
import sys

from mcdenoise.pipeline.errors import PipelineError


def build_parser(prog: str = "python -m pipeline") -> argparse.ArgumentParser:
    """The parser of every subcommand: each package declares its own (``add_commands`` of its
    ``commands`` module); the order here, the pipeline's, is the order of ``--help``."""
    from mcdenoise.clean import commands as clean
    from mcdenoise.evaluate import commands as evaluate
    from mcdenoise.pipeline import commands as core
    from mcdenoise.render import commands as render
    from mcdenoise.train import commands as train

    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for package in (render, clean, train, evaluate, core):
        package.add_commands(sub)
    return parser


OVERRIDE = re.compile(r"^[A-Za-z_][\w.]*=")


def parse_args(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """``parser``'s namespace, with key=value overrides and a scene file taken wherever they stand."""
    # key=value overrides may follow options too (`gt-clean --quiet clean.epochs=3`): argparse
    # stops the positional list at the first option, so collect the rest here.
    args, extra = parser.parse_known_args(argv)
    takes_scene = isinstance(getattr(args, "scene", None), str)
    stray = [a for a in extra if a.startswith("-") or not hasattr(args, "overrides") or not ("=" in a or takes_scene)]
    if stray:
        parser.error(f"unrecognized arguments: {' '.join(stray)}")
    if extra:
        args.overrides = list(args.overrides) + extra
    if takes_scene and hasattr(args, "overrides"):
        # `render-scene --store S X.xml key=value`: argparse hands the first words to the overrides and
        # the last to the scene; the scene is the one word that is not key=value, wherever it stands
        pool, words = [*args.overrides, args.scene], []
        for a in sys.argv[1:] if argv is None else argv:      # in the command line's order: a later override wins
            if a in pool:
                pool.remove(a)
                words.append(a)
        scenes = [w for w in words if not OVERRIDE.match(w)]
        if len(scenes) != 1:
            parser.error(f"{args.command}: expected one scene file and key=value overrides, got: {' '.join(words)}")
        words.remove(scenes[0])
        args.scene, args.overrides = scenes[0], words
    return args


# What a full or read-only disk raises (errno -> what it means for the user).
FILE_SYSTEM = {errno.ENOSPC: ": the disk is full", errno.EDQUOT: ": the disk is full",
               errno.EFBIG: ": the disk is full or the file size is limited", errno.EROFS: ": not writable",
               errno.EACCES: ": not writable", errno.EPERM: ": not writable"}


def main(argv: list[str] | None = None, prog: str = "python -m pipeline") -> int:
    """Run one stage; ``prog`` is the name --help shows (the installed command is ``mcdenoise``)."""
    args = parse_args(build_parser(prog), argv)
    try:
        return args.fn(args)
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.errno not in FILE_SYSTEM:
            raise
        # a stage that writes outside the store's writers (a copy, a folder): the same one line
        where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f)
        print(f"error: {where or 'writing'}: {os.strerror(exc.errno)}{FILE_SYSTEM[exc.errno]}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: finished frames are kept; rerun the same command to continue", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
