"""The dataset stage's subcommands of ``python -m pipeline``: ``dataset``, ``render-scene``, ``bench``, ``plan``.

``add_commands`` declares them (see ``pipeline.commands``); each handler imports what it runs.
"""
from __future__ import annotations

import json

from mcdenoise.pipeline.commands import config, with_config, with_defines, with_quiet
from mcdenoise.pipeline.config import ConfigError


def add_commands(sub) -> None:
    """``dataset``, ``render-scene``, ``bench`` and ``plan``."""
    p = with_config(sub.add_parser("dataset", help="render the dataset into the store"))
    p.add_argument("--shard", default=None, help="i/N: render only the i-th of N contiguous blocks of frames")
    p.add_argument("--time-limit", type=float, default=None, metavar="S",
                   help="start no frame after S seconds (frames in flight finish; a rerun renders the rest)")
    p.add_argument("--splits", default=None, metavar="A,B",
                   help="render only these splits' frames, in this order (e.g. val,train)")
    with_quiet(p, "no progress bar or summary")
    p.set_defaults(fn=_dataset)

    p = with_config(sub.add_parser("render-scene", help="render a Mitsuba 3 XML scene with its own camera into a store"))
    p.add_argument("scene", help="Mitsuba 3 scene XML")
    p.add_argument("--store", default=None, help="store path (default: the config's store)")
    p.add_argument("--resolution", default=None, help="WxH (default: the scene film's size)")
    p.add_argument("--name", default=None, help="scene id in the store (default: ext_<file stem>)")
    with_defines(p)
    p.set_defaults(fn=_render_scene)

    p = with_config(sub.add_parser("bench", help="integrator vs path, dataset time shares, savings of omitted channels"))
    p.add_argument("--out", default="reports/bench", help="folder for bench results (JSON, Markdown)")
    p.set_defaults(fn=_bench)

    p = with_config(sub.add_parser("plan", help="estimate CPU core-hours, disk and wall time of the dataset stage"))
    p.add_argument("--store", default=None, help="calibrate rate and bytes on an existing store's frames")
    p.add_argument("--workers", default="1,2,16,64,256,1024", help="core counts for the wall-time column")
    p.add_argument("--json", action="store_true")
    p.add_argument("--measure", action="store_true", help="measure the model's constants on this machine "
                                                           "(prints JSON for render/plan.py)")
    p.set_defaults(fn=_plan)


def _dataset(args) -> int:
    from .dataset import run
    stats = run(config(args), shard=args.shard, quiet=args.quiet, time_limit_s=args.time_limit,
                splits=args.splits.split(",") if args.splits else None)
    return 1 if stats["failed"] else 0


def _render_scene(args) -> int:
    from .external import parse_defines, render_scene
    cfg = config(args)
    stats = render_scene(args.scene, args.store or cfg.store, cfg, resolution=args.resolution, name=args.name,
                         defines=parse_defines(args.defines))
    return 1 if stats["failed"] else 0


def _bench(args) -> int:
    from .bench import run_bench
    run_bench(config(args), out=args.out)
    return 0


def _plan(args) -> int:
    from .plan import measure, run_plan
    cfg = config(args)
    if args.measure:
        print(json.dumps(measure(cfg), indent=1))
        return 0
    try:
        workers = tuple(int(v) for v in args.workers.split(","))
    except ValueError:
        raise ConfigError(f"--workers {args.workers!r}: expected comma-separated core counts, e.g. 1,16,256") from None
    run_plan(cfg, title=args.config or "defaults", store=args.store, workers=workers, as_json=args.json)
    return 0
