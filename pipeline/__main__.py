"""Command line: ``python -m pipeline <stage> [--config FILE] [key=value ...]``.

Every stage reads the same typed config (``pipeline.config``); ``key=value`` overrides any key
(dotted for sections: ``dataset.scenes=4``). Errors in input (config, store, scene files,
checkpoints: every ``pipeline.errors.PipelineError``) print one line naming the culprit and exit
with status 2; nothing half-written is left behind.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mcdenoise.pipeline.config import ConfigError, documentation_markdown, load_config, to_dict
from mcdenoise.pipeline.errors import PipelineError


def _config(args):
    return load_config(args.config, args.overrides)


def cmd_dataset(args) -> int:
    from mcdenoise.render.dataset import run
    stats = run(_config(args), shard=args.shard, quiet=args.quiet)
    return 1 if stats["failed"] else 0


def cmd_inspect(args) -> int:
    from mcdenoise.pipeline.inspect import format_report, inspect_store
    report = inspect_store(args.store, frame=args.frame)
    print(json.dumps(report, indent=1, sort_keys=True) if args.json else format_report(report))
    return 0


def cmd_render_scene(args) -> int:
    from mcdenoise.render.external import render_scene
    cfg = _config(args)
    stats = render_scene(args.scene, args.store or cfg.store, cfg, resolution=args.resolution, name=args.name)
    return 1 if stats["failed"] else 0


def cmd_gt_clean(args) -> int:
    from mcdenoise.clean.cli import cmd_gt_clean as run
    return run(_config(args), quiet=args.quiet)


def _spp(text: str):
    if text == "any":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a sample count (4, 16, 64) or 'any', got {text!r}") from None


def cmd_train(args) -> int:
    cfg = _config(args)
    if args.model == "isik":
        from mcdenoise.clean.cli import cmd_train_isik
        return cmd_train_isik(cfg, args.spp, quiet=args.quiet)
    if args.model == "afgsa":
        from mcdenoise.train.afgsa import train as train_afgsa
        train_afgsa(cfg, args.spp, quiet=args.quiet)
        return 0
    if args.model == "oidn_ft":
        from mcdenoise.train.oidn_ft import train as train_oidn_ft
        train_oidn_ft(cfg, args.spp, quiet=args.quiet)
        return 0
    from mcdenoise.train.cli import cmd_train as train_diffusion
    return train_diffusion(cfg, args.spp, quiet=args.quiet)


def cmd_pretrain(args) -> int:
    from mcdenoise.train.cli import cmd_pretrain as run
    return run(_config(args), quiet=args.quiet)


def cmd_pack(args) -> int:
    from mcdenoise.train.cli import cmd_pack as run
    return run(_config(args), args.split or ["train", "val"], quiet=args.quiet)


def cmd_export(args) -> int:
    from pathlib import Path

    from mcdenoise.train.export import export, export_oidn
    if args.format == "oidn":
        export_oidn(_config(args), Path(args.out) if args.out else None, quiet=args.quiet, config=args.config,
                    overrides=args.overrides)
        return 0
    if args.spp is None:
        raise ConfigError("export --format model needs --spp (the diffusion run: 4, 16, 64 or any)")
    export(_config(args), args.spp, Path(args.out or "train/shipped"), quiet=args.quiet, config=args.config,
           overrides=args.overrides)
    return 0


def cmd_gpu_prepare(args) -> int:
    from pathlib import Path

    from mcdenoise.train.gpu_recipe import prepare
    prepare(_config(args), Path(args.out), args.train_crops, args.val_crops, args.side, wheels=not args.no_wheels)
    return 0


def cmd_denoise(args) -> int:
    from mcdenoise.train.cli import cmd_denoise as run, cmd_denoise_oidn
    if args.method != "ours" or args.oidn_weights:
        return cmd_denoise_oidn(_config(args), args.frame, args.exr, args.out, args.method, args.oidn_weights,
                                spp=args.spp, quiet=args.quiet)
    return run(_config(args), args.spp, args.frame, args.exr, args.out, args.skip, args.seed,
               base_only=args.base_only, quiet=args.quiet, steps=args.steps, samples=args.samples)


def cmd_clean_report(args) -> int:
    from mcdenoise.clean.report import run_report
    run_report(_config(args), out=args.out, spp=args.spp)
    return 0


def cmd_afgsa_report(args) -> int:
    from mcdenoise.train.afgsa_report import default_runs, run_afgsa_report
    cfg = _config(args)
    runs = default_runs(cfg, args.spp)
    for text in args.runs or []:
        label, sep, folder = text.partition("=")
        if not sep or not label or not folder:
            raise ConfigError(f"--run {text!r}: expected LABEL=FOLDER")
        runs[label] = Path(folder)
    run_afgsa_report(cfg, spp=args.spp, out=args.out, runs=runs, crops=cfg.eval.crops)
    return 0


def cmd_eval(args) -> int:
    from mcdenoise.evaluate.run import run_eval
    spps = None
    if args.spp:
        try:
            spps = [int(v) for v in args.spp.split(",") if v.strip()]
        except ValueError:
            raise ConfigError(f"--spp {args.spp!r}: expected sample counts such as 4 or 4,16,64") from None
    run_eval(_config(args), spps=spps, scenes=args.scenes, out=args.out, quiet=args.quiet)
    return 0


def cmd_stability(args) -> int:
    from mcdenoise.evaluate.stability import run_stability
    data = run_stability(_config(args), out=args.out, quiet=args.quiet)
    failed = sum(c["status"] not in ("ok", "not available") for r in data["results"].values() for c in r.values())
    return 1 if failed else 0


def cmd_config(args) -> int:
    if args.doc:
        print(documentation_markdown(), end="")
        return 0
    import yaml
    print(yaml.safe_dump(to_dict(_config(args)), sort_keys=False), end="")
    return 0


def cmd_bench_denoise(args) -> int:
    from mcdenoise.train.bench import run, run_oidn
    cfg = _config(args)
    run(cfg, spp=args.spp, side=args.side, out=args.out)
    run_oidn(cfg, out=args.out)
    return 0


def cmd_bench(args) -> int:
    from mcdenoise.render.bench import run_bench
    run_bench(_config(args), out=args.out)
    return 0


def cmd_verify(args) -> int:
    from mcdenoise.pipeline.verify import bytes_table, measure_bytes, run_verify
    if args.bytes:
        print(bytes_table(measure_bytes(args.store, args.bytes)))
        return 0
    return run_verify(args.store, quiet=args.quiet, pixels=not args.headers_only, jobs=args.jobs)


def cmd_plan(args) -> int:
    from mcdenoise.render.plan import measure, run_plan
    cfg = _config(args)
    if args.measure:
        print(json.dumps(measure(cfg), indent=1))
        return 0
    try:
        workers = tuple(int(v) for v in args.workers.split(","))
    except ValueError:
        raise ConfigError(f"--workers {args.workers!r}: expected comma-separated core counts, e.g. 1,16,256") from None
    run_plan(cfg, title=args.config or "defaults", store=args.store, workers=workers, as_json=args.json)
    return 0


def _with_config(p):
    """Add the arguments of every stage that reads the config: --config FILE and key=value overrides."""
    p.add_argument("--config", default=None, help="YAML config (default: built-in defaults)")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="override config keys")
    return p


def _dataset_parsers(sub) -> None:
    """Subcommands for the dataset and GT-cleaner stages."""
    p = _with_config(sub.add_parser("dataset", help="render the dataset into the store"))
    p.add_argument("--shard", default=None, help="i/N: render only the i-th of N contiguous blocks of frames")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.set_defaults(fn=cmd_dataset)

    p = _with_config(sub.add_parser("gt-clean", help="train the GT cleaner (resumable), then write gt_clean for every frame"))
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(fn=cmd_gt_clean)


def _train_parsers(sub) -> None:
    """Subcommands for the denoisers: training, its preparation (pretrain, GPU recipe, packs), export, inference."""
    p = _with_config(sub.add_parser("train", help="train a denoiser: --model diffusion (ours), oidn_ft (OIDN "
                                                  "fine-tuned), isik or afgsa (baselines); diffusion runs under "
                                                  "torchrun for DDP"))
    p.add_argument("--model", default="diffusion", choices=["diffusion", "oidn_ft", "isik", "afgsa"],
                   help="which denoiser")
    p.add_argument("--spp", type=_spp, required=True,
                   help="sample count of the noisy input (4, 16, 64), or 'any': one diffusion or AFGSA model "
                        "for all")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(fn=cmd_train)

    p = _with_config(sub.add_parser("pretrain", help="train the stand-in base (IF-II layout, restoration prior)"))
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(fn=cmd_pretrain)

    p = _with_config(sub.add_parser("export", help="copy a trained diffusion run into a self-contained model folder "
                                                   "(the shipped model: train/shipped), or (--format oidn) an "
                                                   "oidn_ft run into a .tza file OIDN loads as its weights"))
    p.add_argument("--format", default="model", choices=["model", "oidn"],
                   help="model: the diffusion run as a model folder; oidn: the oidn_ft run of oidn_ft.network as "
                        "float16 OIDN weights (.tza)")
    p.add_argument("--spp", type=_spp, default=None, help="the diffusion run (diffusion_spp<N> or any); --format model")
    p.add_argument("--out", default=None, help="the model folder to write (default train/shipped); --format oidn: a "
                                               ".tza file or a folder (default <runs>/oidn_ft_<network>.tza)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(fn=cmd_export)

    p = _with_config(sub.add_parser("gpu-prepare", help="write .gpu/ for the GPU recipe (train/gpu_recipe.py): crop "
                                                        "packs from the training packs and the wheels a bare GPU "
                                                        "machine lacks"))
    p.add_argument("--out", default=".gpu")
    p.add_argument("--train-crops", type=int, default=48)
    p.add_argument("--val-crops", type=int, default=12)
    p.add_argument("--side", type=int, default=48)
    p.add_argument("--no-wheels", action="store_true", help="crop packs only")
    p.set_defaults(fn=cmd_gpu_prepare)

    p = _with_config(sub.add_parser("pack", help="decode the store once into compact training packs (train/pack.py)"))
    p.add_argument("--split", action="append", default=None, help="split to pack (repeatable; default: train, val)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(fn=cmd_pack)

    p = _with_config(sub.add_parser("denoise", help="denoise a store frame or an EXR with a trained diffusion run"))
    p.add_argument("--spp", type=_spp, default=None,
                   help="the input's samples per pixel (and the run diffusion_spp<N>, else diffusion_sppany, else the "
                        "shipped model); required with --frame; with --exr: the EXR header's if it has one, else 16")
    p.add_argument("--frame", default=None, help="SCENE/FRAME of the store, e.g. s00000/000")
    p.add_argument("--exr", default=None, help="an EXR with R,G,B (and optionally our feature layers)")
    p.add_argument("--out", required=True, help="output EXR")
    p.add_argument("--skip", type=int, default=None, help="sampler steps to skip (default: the run's)")
    p.add_argument("--steps", type=int, default=None, help="sampler steps, refine formulation (default: the run's)")
    p.add_argument("--samples", type=int, default=None,
                   help="average K samples; their per-pixel standard deviation goes to the 'std' layer")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--base-only", action="store_true", help="the ablation: base without the Control Module")
    p.add_argument("--method", default="ours", choices=["ours", "oidn", "oidn_ft"],
                   help="ours: the diffusion denoiser; oidn: OIDN's built-in network; oidn_ft: the oidn_ft run "
                        "(make train MODEL=oidn_ft) of the network the input's layers match, run by OIDN itself")
    p.add_argument("--oidn-weights", default=None, metavar="FILE.tza",
                   help="run OIDN with these weights (export --format oidn writes them) on the input's layers")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(fn=cmd_denoise)


def _report_parsers(sub) -> None:
    """Subcommands for the reports: cleaner, AFGSA, evaluation, stability."""
    p = _with_config(sub.add_parser("clean-report", help="GT1 vs GT_clean against GT2 on val/test, crop grid; "
                                                         "--spp N adds the Isik baseline on the test split"))
    p.add_argument("--out", default="reports/cleaner")
    p.add_argument("--spp", type=int, default=None)
    p.set_defaults(fn=cmd_clean_report)

    p = _with_config(sub.add_parser("afgsa-report", help="AFGSA trained against GT_clean vs against GT1, both "
                                                         "scored against GT_clean: table and crop grid"))
    p.add_argument("--spp", type=int, default=4)
    p.add_argument("--out", default="reports/afgsa")
    p.add_argument("--run", action="append", default=None, metavar="LABEL=FOLDER", dest="runs",
                   help="another AFGSA run folder to compare (e.g. the adv_weight=0 ablation); repeatable")
    p.set_defaults(fn=cmd_afgsa_report)

    p = _with_config(sub.add_parser("eval", help="every method on the test frames per spp: tables, error vs time, "
                                                 "crops (reports/<run>/)"))
    p.add_argument("--spp", default=None, help="sample counts, comma-separated, e.g. 4 or 4,16 (default: eval.spp)")
    p.add_argument("--scene", action="append", default=None, metavar="XML", dest="scenes",
                   help="a Mitsuba 3 scene to render into the store (split 'external') and report separately; "
                        "repeat for several")
    p.add_argument("--out", default=None, help="report folder (default: eval.out or reports/<runs name>)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(fn=cmd_eval)

    p = _with_config(sub.add_parser("stability", help="every method on synthetic edge cases (fireflies, NaN, sizes, ...)"))
    p.add_argument("--out", default=None, help="report folder (default: as eval)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(fn=cmd_stability)


def _tool_parsers(sub) -> None:
    """Subcommands for store and scene tools, the config, benchmarks and the plan."""
    p = sub.add_parser("inspect", help="describe a store (frames, channels, constants, timings, NaN/Inf)")
    p.add_argument("store")
    p.add_argument("--frame", default=None, help="SCENE/FRAME, e.g. s00000/000: details of one frame")
    p.add_argument("--json", action="store_true")
    p.set_defaults(fn=cmd_inspect)

    p = _with_config(sub.add_parser("render-scene", help="render a Mitsuba 3 XML scene with its own camera into a store"))
    p.add_argument("scene", help="Mitsuba 3 scene XML")
    p.add_argument("--store", default=None, help="store path (default: the config's store)")
    p.add_argument("--resolution", default=None, help="WxH (default: the scene film's size)")
    p.add_argument("--name", default=None, help="scene id in the store (default: ext_<file stem>)")
    p.set_defaults(fn=cmd_render_scene)

    p = _with_config(sub.add_parser("config", help="print the resolved config, or --doc the key reference"))
    p.add_argument("--doc", action="store_true")
    p.set_defaults(fn=cmd_config)

    p = _with_config(sub.add_parser("bench", help="integrator vs path, dataset time shares, savings of omitted channels"))
    p.add_argument("--out", default="reports/bench", help="folder for bench results (JSON, Markdown)")
    p.set_defaults(fn=cmd_bench)

    p = _with_config(sub.add_parser("bench-denoise", help="diffusion inference time at 1/3/9/27 steps, 128² and per MP; OIDN "
                                                              "(built-in, exported weights, PyTorch twin) per 128² and 1080p"))
    p.add_argument("--spp", type=int, default=4, help="use the trained run of this spp when there is one")
    p.add_argument("--side", type=int, default=128, help="frame side of the per-frame timing")
    p.add_argument("--out", default="reports/bench")
    p.set_defaults(fn=cmd_bench_denoise)

    p = sub.add_parser("verify", help="check every file of a store (readable, channels, shapes, checksums, "
                                      "manifests, gt_clean hashes, leftover .tmp); exit 1 on any problem")
    p.add_argument("store")
    p.add_argument("--headers-only", action="store_true", help="skip pixel data and checksums (fast)")
    p.add_argument("--jobs", type=int, default=1, help="check scenes in this many processes")
    p.add_argument("--quiet", action="store_true", help="only the summary line")
    p.add_argument("--bytes", type=int, default=0, metavar="N",
                   help="instead of checking: bytes per channel group of N frames, as stored and re-encoded compact")
    p.set_defaults(fn=cmd_verify)

    p = _with_config(sub.add_parser("plan", help="estimate CPU core-hours, disk and wall time of the dataset stage"))
    p.add_argument("--store", default=None, help="calibrate rate and bytes on an existing store's frames")
    p.add_argument("--workers", default="1,2,16,64,256,1024", help="core counts for the wall-time column")
    p.add_argument("--json", action="store_true")
    p.add_argument("--measure", action="store_true", help="measure the model's constants on this machine "
                                                           "(prints JSON for render/plan.py)")
    p.set_defaults(fn=cmd_plan)


def main(argv: list[str] | None = None, prog: str = "python -m pipeline") -> int:
    """Run one stage; ``prog`` is the name --help shows (the installed command is ``mcdenoise``)."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    # The order of these calls is the order of the subcommands in --help.
    _dataset_parsers(sub)
    _train_parsers(sub)
    _report_parsers(sub)
    _tool_parsers(sub)

    # key=value overrides may follow options too (`gt-clean --quiet clean.epochs=3`): argparse
    # stops the positional list at the first option, so collect the rest here.
    args, extra = parser.parse_known_args(argv)
    stray = [a for a in extra if a.startswith("-") or "=" not in a or not hasattr(args, "overrides")]
    if stray:
        parser.error(f"unrecognized arguments: {' '.join(stray)}")
    if extra:
        args.overrides = list(args.overrides) + extra
    try:
        return args.fn(args)
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: finished frames are kept; rerun the same command to continue", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
