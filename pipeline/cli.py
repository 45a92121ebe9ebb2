"""The command line: ``python -m pipeline <stage> [--config FILE] [key=value ...]``, in one layer.

Every subcommand is declared here (its flags and help) with its handler, which turns the parsed flags into
one call of the stage that runs it (``render``, ``clean``, ``train``, ``evaluate``, or the core's own store
tools), imported when the command runs: building the parser loads no torch, numpy or Mitsuba. Every stage
reads the same typed config (``pipeline.config``); ``key=value`` overrides any key (dotted for sections:
``dataset.scenes=4``). Errors in input (config, store, scene files, checkpoints: every
``pipeline.errors.PipelineError``) print one line naming the culprit and exit with status 2; nothing
half-written is left behind.
"""
from __future__ import annotations

import argparse
import errno
import json
import os
import re
import sys
from pathlib import Path

from .config import Config, ConfigError, documentation_markdown, load_config, to_dict
from .errors import PipelineError

DESCRIPTION = ("Render a Monte Carlo denoising dataset with Mitsuba 3, clean its ground truth, train and score the "
               "denoisers, and denoise EXRs. Every stage reads --config FILE and key=value overrides.")


def build_parser(prog: str = "python -m pipeline") -> argparse.ArgumentParser:
    """The parser of every subcommand, in the pipeline's order (the order of ``--help``)."""
    parser = argparse.ArgumentParser(prog=prog, description=DESCRIPTION)
    sub = parser.add_subparsers(dest="command", required=True)
    for declare in (_render_commands, _clean_commands, _training_commands, _inference_commands, _report_commands,
                    _evaluate_commands, _core_commands):
        declare(sub)
    return parser


# ---- options every stage's subcommands share ---------------------------------------------------------


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


def with_quiet(p: argparse.ArgumentParser, text: str = "no progress bars or per-epoch lines; the summary line only"
               ) -> argparse.ArgumentParser:
    """Add --quiet, the flag of every subcommand that reports progress (``text``: its help)."""
    p.add_argument("--quiet", action="store_true", help=text)
    return p


def command(sub, name: str, summary: str, **kwargs) -> argparse.ArgumentParser:
    """A subcommand whose ``--help`` page opens with the one line the top-level list shows (``summary``)."""
    return sub.add_parser(name, help=summary, description=kwargs.pop("description", summary[0].upper() + summary[1:]),
                          **kwargs)


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



# ---- the dataset stage: dataset, render-scene, bench, plan -------------------------------------------------


def _render_commands(sub) -> None:
    """``dataset``, ``render-scene``, ``bench`` and ``plan``."""
    p = with_config(command(sub, "dataset", "render the dataset into the store"))
    p.add_argument("--shard", default=None, help="i/N: render only the i-th of N contiguous blocks of frames")
    p.add_argument("--time-limit", type=float, default=None, metavar="S",
                   help="start no frame after S seconds (frames in flight finish; a rerun renders the rest)")
    p.add_argument("--splits", default=None, metavar="A,B",
                   help="render only these splits' frames, in this order (e.g. val,train)")
    with_quiet(p, "no progress bar or summary")
    p.set_defaults(fn=_dataset)

    p = with_config(command(sub, "render-scene", "render a Mitsuba 3 XML scene with its own camera into a store"))
    p.add_argument("scene", help="Mitsuba 3 scene XML")
    p.add_argument("--store", default=None, help="store path (default: the config's store)")
    p.add_argument("--resolution", default=None, help="WxH (default: the scene film's size)")
    p.add_argument("--name", default=None, help="scene id in the store (default: ext_<file stem>)")
    p.add_argument("--frames", type=int, default=1, help="frames 000..N-1 along a camera path (default: 1)")
    p.add_argument("--move", default=None, metavar="KIND:AMOUNT",
                   help="the path of --frames: orbit:DEGREES about the look-at target, or dolly:FRACTION of the "
                        "distance towards it (default: from the scene's first camera to its second, if it has one)")
    with_defines(p)
    p.set_defaults(fn=_render_scene)

    p = with_config(command(sub, "bench", "integrator vs path, dataset time shares, savings of omitted channels"))
    p.add_argument("--out", default="reports/bench", help="folder for bench results (JSON, Markdown)")
    p.set_defaults(fn=_bench)

    p = with_config(command(sub, "plan", "estimate CPU core-hours, disk and wall time of the dataset stage"))
    p.add_argument("--store", default=None, help="calibrate rate and bytes on an existing store's frames")
    p.add_argument("--workers", default="1,2,16,64,256,1024", help="core counts for the wall-time column")
    p.add_argument("--json", action="store_true", help="print the plan as JSON instead of a table")
    p.add_argument("--measure", action="store_true", help="measure the model's constants on this machine "
                                                           "(prints JSON for render/plan.py)")
    p.set_defaults(fn=_plan)


def _dataset(args) -> int:
    from mcdenoise.render.dataset import run
    stats = run(config(args), shard=args.shard, quiet=args.quiet, time_limit_s=args.time_limit,
                splits=args.splits.split(",") if args.splits else None)
    return 1 if stats["failed"] else 0


def _render_scene(args) -> int:
    from mcdenoise.render.external import parse_defines, render_scene
    cfg = config(args)
    stats = render_scene(args.scene, args.store or cfg.store, cfg, resolution=args.resolution, name=args.name,
                         defines=parse_defines(args.defines), frames=args.frames, move=args.move)
    return 1 if stats["failed"] else 0


def _bench(args) -> int:
    from mcdenoise.render.bench import run_bench
    run_bench(config(args), out=args.out)
    return 0


def _plan(args) -> int:
    from mcdenoise.render.plan import measure, run_plan
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



# ---- the cleaner: gt-clean, clean-report -------------------------------------------------------------------


def _clean_commands(sub) -> None:
    """``gt-clean`` and ``clean-report``."""
    p = with_config(command(sub, "gt-clean", "train the GT cleaner (resumable), then write gt_clean for every frame"))
    with_quiet(p)
    p.set_defaults(fn=_gt_clean)

    p = with_config(command(sub, "clean-report", "GT1 vs GT_clean against GT2 on val/test, crop grid; "
                                                         "--spp N adds the Isik baseline on the test split"))
    p.add_argument("--out", default="reports/cleaner", help="the report folder")
    p.add_argument("--spp", type=int, default=None, help="also score the Isik baseline at this sample count (needs its "
                                                         "run: make train MODEL=isik)")
    p.set_defaults(fn=_clean_report)


def _gt_clean(args) -> int:
    from mcdenoise.clean.train import gt_clean
    return gt_clean(config(args), quiet=args.quiet)


def _clean_report(args) -> int:
    from mcdenoise.clean.report import run_report
    run_report(config(args), out=args.out, spp=args.spp)
    return 0



# ---- the denoisers: train, export, pack, denoise, afgsa-report, bench-denoise ------------------------------




def _training_commands(sub) -> None:
    p = with_config(command(sub, "train", "train a denoiser: --model diffusion (ours), oidn_ft (OIDN "
                                                 "fine-tuned), isik or afgsa (baselines); diffusion runs under "
                                                 "torchrun for DDP"))
    p.add_argument("--model", default="diffusion", choices=["diffusion", "oidn_ft", "isik", "afgsa"],
                   help="which denoiser")
    p.add_argument("--spp", type=spp, required=True,
                   help="sample count of the noisy input (4, 16, 64), or 'any': one diffusion or AFGSA model "
                        "for all")
    with_quiet(p)
    p.set_defaults(fn=_train)

    p = with_config(command(sub, "export", "copy a trained diffusion run into a self-contained model folder "
                                                  "(the shipped model: train/shipped), or (--format oidn) an "
                                                  "oidn_ft run into a .tza file OIDN loads as its weights"))
    p.add_argument("--format", default="model", choices=["model", "oidn"],
                   help="model: the diffusion run as a model folder; oidn: the oidn_ft run of oidn_ft.network as "
                        "float16 OIDN weights (.tza)")
    p.add_argument("--spp", type=spp, default=None, help="the diffusion run (diffusion_spp<N> or any); --format model")
    p.add_argument("--out", default=None, help="the model folder to write (default train/shipped); --format oidn: a "
                                               ".tza file or a folder (default <runs>/oidn_ft_<network>.tza)")
    p.add_argument("--base-blend", type=float, default=None,
                   help="instead: move the base of an exported model (--from) to OIDN + this x what fine-tuning "
                        "changed (oidn_ft.blend's knob, after training), written to --out (default: --from)")
    p.add_argument("--base", default=None,
                   help="instead: replace the frozen base of an exported model (--from) by this .tza of the same "
                        "OIDN network (e.g. an --format oidn export), keeping its Control Module; to --out")
    p.add_argument("--strength", type=float, default=None,
                   help="instead: make an exported model (--from) apply this fraction (0..1) of what its Control "
                        "Module changes to its base's output (model.json strength), written to --out (default: --from)")
    p.add_argument("--fit-sigma", action="store_true",
                   help="instead: fit σ's scale of an exported model on OIDN's network (--from) again, on the val "
                        "frames of the config's store at the model's strength, written to --out (default: --from)")
    p.add_argument("--from", dest="from_model", default="train/shipped",
                   help="the model folder --base-blend moves, --base changes, --strength sets or --fit-sigma fits")
    with_quiet(p)
    p.set_defaults(fn=_export)


def _sequence_options(p) -> None:
    """denoise's --sequence and the options that go with it."""
    p.add_argument("--sequence", default=None, metavar="PATTERN",
                   help="a rendered sequence, e.g. 'in/frame_####.exr' (# the zero-padded frame number): every frame "
                        "denoised (--method ours or oidn_prefilter) and blended with its warped history, using "
                        "Blender's Vector pass, or the EXR headers' worldToCamera/worldToNDC and the depth channel Z "
                        "(without either, frame by frame, said in one line); --out is then a pattern too, e.g. 'out/####.exr'")
    p.add_argument("--temporal-weight", type=float, default=None,
                   help="--sequence: the new frame's share of the blend (1: no history; default eval.temporal_weight)")
    p.add_argument("--temporal-window", type=int, default=None,
                   help="--sequence: frames over which the noisy diffuse light is averaged before denoising (1: none; "
                        "default eval.temporal_window)")
    p.add_argument("--ahead", type=int, default=None,
                   help="--sequence: frames after each one averaged too, and the filter's history taken from both "
                        "sides (0: the frames before alone and the causal filter, as frames that arrive one at a "
                        "time; default eval.temporal_ahead)")


def _inference_commands(sub) -> None:
    p = with_config(command(sub, "pack", "decode the store once into compact training packs (train/data.py)"))
    p.add_argument("--split", action="append", default=None, help="split to pack (repeatable; default: train, val)")
    with_quiet(p)
    p.set_defaults(fn=_pack)

    p = with_config(command(sub, "denoise", "denoise a store frame or an EXR with a trained diffusion run",
                                   description="Denoise a store frame or an EXR with a trained diffusion run. The "
                                               "weights: without --config, the shipped model (train/shipped); with "
                                               "one, the config's run of the input's sample count "
                                               "(<runs>/diffusion_spp<N>, else <runs>/diffusion_sppany; runs is "
                                               "the config's 'runs' key) if it was trained on the config's store, "
                                               "else train/shipped. The summary line names the weights that ran."))
    p.add_argument("--spp", type=spp, default=None,
                   help="the input's samples per pixel (and the run diffusion_spp<N>, else diffusion_sppany, else the "
                        "shipped model); required with --frame; with --exr: the EXR header's if it has one, else 16")
    p.add_argument("--frame", default=None, help="SCENE/FRAME of the store, e.g. s00000/000 (render-scene prints "
                                                 "the command that denoises what it rendered)")
    p.add_argument("--store", default=None, help="the store --frame reads (default: the config's store)")
    p.add_argument("--exr", default=None, help="an EXR with R,G,B (and optionally our feature layers)")
    _sequence_options(p)
    p.add_argument("--out", required=True, help="output EXR (with --sequence: a pattern with one run of #)")
    p.add_argument("--skip", type=int, default=None, help="sampler steps to skip (default: the run's)")
    p.add_argument("--steps", type=int, default=None, help="sampler steps (default: the model's)")
    p.add_argument("--samples", type=int, default=None,
                   help="average K samples; their per-pixel standard deviation goes to the 'std' layer")
    p.add_argument("--seed", type=int, default=None, help="the sampler's noise seed (default: the config's seed)")
    p.add_argument("--base-only", action="store_true", help="the ablation: base without the Control Module")
    p.add_argument("--strength", type=float, default=None,
                   help="the fraction (0..1) of what the Control Module changes that is applied to its base's output "
                        "(a model on OIDN's network; default: the model's, model.json strength, else 1)")
    p.add_argument("--method", default="ours", choices=["ours", "oidn", "oidn_prefilter", "oidn_ft", "oidn_ft_prefilter"],
                   help="ours: the diffusion denoiser; oidn: OIDN's built-in network; oidn_prefilter: OIDN's "
                        "final-frame mode (albedo and normal prefiltered by OIDN, then cleanAux; needs both); "
                        "oidn_ft: the oidn_ft run "
                        "(make train MODEL=oidn_ft) of the network the input's layers match, run by OIDN itself; "
                        "oidn_ft_prefilter: the oidn_ft run of OIDN's final-frame network (oidn_ft.network="
                        "rt_hdr_calb_cnrm_large), run as oidn_prefilter")
    p.add_argument("--oidn-weights", default=None, metavar="FILE.tza",
                   help="run OIDN with these weights (export --format oidn writes them) on the input's layers")
    p.add_argument("--device", default=None, help="torch device of ours: auto (CUDA if there is one), cuda, cpu "
                                                  "(default: diffusion.device)")
    p.add_argument("--precision", default="auto", choices=("auto", "fp32", "fp16", "bf16"),
                   help="ours' networks: auto is fp16 on CUDA (about 70 dB from fp32), fp32 on the CPU")
    p.add_argument("--ensemble", type=int, default=1, choices=(1, 2, 4, 8),
                   help="average the denoiser's outputs on N flipped/transposed copies of the input (N times its "
                        "time; see docs/evaluation.md for what it gains)")
    with_quiet(p)
    p.set_defaults(fn=_denoise)


def _report_commands(sub) -> None:
    p = with_config(command(sub, "afgsa-report", "AFGSA trained against GT_clean vs against GT1, both "
                                                        "scored against GT_clean: table and crop grid"))
    p.add_argument("--spp", type=int, default=4, help="the sample count of the noisy input")
    p.add_argument("--out", default="reports/afgsa", help="the report folder")
    p.add_argument("--run", action="append", default=None, metavar="LABEL=FOLDER", dest="runs",
                   help="another AFGSA run folder to compare (e.g. the adv_weight=0 ablation); repeatable")
    p.set_defaults(fn=_afgsa_report)

    p = with_config(command(sub, "bench-denoise", "seconds per frame of ours, its base and OIDN's own engine at "
                                                         "256², 1080p (and 4K on CUDA)"))
    p.add_argument("--spp", type=int, default=4, help="use the trained run of this spp when there is one")
    p.add_argument("--sizes", default=None, help="frame sizes WxH, comma-separated (default: 256x256,1920x1080; "
                                                "with CUDA also 3840x2160)")
    p.add_argument("--device", default=None, help="auto, cuda or cpu (default: diffusion.device)")
    p.add_argument("--precision", default="auto", choices=("auto", "fp32", "fp16", "bf16"),
                   help="the networks' precision: auto is fp16 on CUDA, fp32 on the CPU")
    p.add_argument("--repeats", type=int, default=2, help="timed runs per case (the best is reported)")
    p.add_argument("--out", default="reports/bench", help="the folder of the results (JSON, Markdown)")
    p.set_defaults(fn=_bench_denoise)




def _train(args) -> int:
    cfg = config(args)
    if args.model == "isik":     # the cleaner's network on noisy input, against GT_clean
        from mcdenoise.clean.train import train as train_isik
        train_isik(cfg, mode="baseline", spp=args.spp if str(args.spp) == "any" else int(args.spp), quiet=args.quiet)
        return 0
    if args.model == "afgsa":
        from mcdenoise.train.baselines.afgsa import train as train_afgsa
        train_afgsa(cfg, args.spp, quiet=args.quiet)
        return 0
    if args.model == "oidn_ft":
        from mcdenoise.train.baselines.oidn_ft import train as train_oidn_ft
        train_oidn_ft(cfg, args.spp, quiet=args.quiet)
        return 0
    from mcdenoise.train.train import train
    train(cfg, args.spp, quiet=args.quiet)
    return 0


def _export(args) -> int:
    from mcdenoise.train.export import export, export_oidn, fit_sigma, rebase, set_strength, swap_base
    if args.fit_sigma:
        fit_sigma(config(args), Path(args.from_model), Path(args.out) if args.out else None, quiet=args.quiet,
                  config=args.config, overrides=args.overrides)
        return 0
    if args.strength is not None:
        set_strength(Path(args.from_model), args.strength, Path(args.out) if args.out else None, quiet=args.quiet)
        return 0
    if args.base is not None:
        swap_base(Path(args.from_model), Path(args.base), Path(args.out) if args.out else None, quiet=args.quiet)
        return 0
    if args.base_blend is not None:
        rebase(Path(args.from_model), args.base_blend, Path(args.out) if args.out else None,
               config(args).oidn.weights, quiet=args.quiet)
        return 0
    if args.format == "oidn":
        export_oidn(config(args), Path(args.out) if args.out else None, quiet=args.quiet, config=args.config,
                    overrides=args.overrides)
        return 0
    if args.spp is None:
        raise ConfigError("export --format model needs --spp (the diffusion run: 4, 16, 64 or any)")
    export(config(args), args.spp, Path(args.out or "train/shipped"), quiet=args.quiet, config=args.config,
           overrides=args.overrides)
    return 0


def _pack(args) -> int:
    from mcdenoise.train.data import cmd_pack
    return cmd_pack(config(args), args.split or ["train", "val"], quiet=args.quiet)


def _denoise(args) -> int:
    from mcdenoise.train.infer import cmd_denoise, cmd_denoise_oidn
    from mcdenoise.train.model import SHIPPED_MODEL
    if args.store is not None:
        args.overrides = [*args.overrides, f"store={args.store}"]
    # without a config (or a runs folder) the shipped model, whatever a runs folder here holds
    own_runs = args.config is not None or any(o.startswith(("runs=", "diffusion.model=")) for o in args.overrides)
    model = None if own_runs else SHIPPED_MODEL
    if args.sequence is not None:
        from mcdenoise.train.sequence import cmd_denoise_sequence
        if args.exr is not None or args.frame is not None:
            raise ConfigError("give one of --sequence PATTERN, --exr FILE or --frame SCENE/FRAME")
        return cmd_denoise_sequence(config(args), args.sequence, args.out, args.spp, method=args.method,
                                    weight=args.temporal_weight, window=args.temporal_window, ahead=args.ahead,
                                    quiet=args.quiet,
                                    model=model, device=args.device,
                                    precision=args.precision, seed=args.seed)
    if args.method != "ours" or args.oidn_weights:
        return cmd_denoise_oidn(config(args), args.frame, args.exr, args.out, args.method, args.oidn_weights,
                                spp=args.spp, quiet=args.quiet, ensemble=args.ensemble)
    return cmd_denoise(config(args), args.spp, args.frame, args.exr, args.out, args.skip, args.seed,
                       base_only=args.base_only, quiet=args.quiet, steps=args.steps, samples=args.samples,
                       ensemble=args.ensemble, strength=args.strength, device=args.device, precision=args.precision,
                       model=model)


def _afgsa_report(args) -> int:
    from mcdenoise.train.baselines.afgsa_report import default_runs, run_afgsa_report
    cfg = config(args)
    runs = default_runs(cfg, args.spp)
    for text in args.runs or []:
        label, sep, folder = text.partition("=")
        if not sep or not label or not folder:
            raise ConfigError(f"--run {text!r}: expected LABEL=FOLDER")
        runs[label] = Path(folder)
    run_afgsa_report(cfg, spp=args.spp, out=args.out, runs=runs, crops=cfg.eval.crops)
    return 0


def _bench_denoise(args) -> int:
    from mcdenoise.train.bench import parse_sizes, run
    if args.sizes:
        try:
            parse_sizes(args.sizes)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    run(config(args), spp=args.spp, sizes=args.sizes, device=args.device, precision=args.precision,
        repeats=args.repeats, out=args.out)
    return 0



# ---- evaluation: eval, stability ---------------------------------------------------------------------------


def _evaluate_commands(sub) -> None:
    """``eval`` and ``stability``."""
    p = with_config(command(sub, "eval", "every method on the test frames per spp: tables, error vs time, "
                                                "crops (reports/<run>/)"))
    p.add_argument("--spp", default=None, help="sample counts, comma-separated, e.g. 4 or 4,16 (default: eval.spp)")
    p.add_argument("--scene", action="append", default=None, metavar="XML", dest="scenes",
                   help="a Mitsuba 3 scene to render into the store (split 'external') and report separately; "
                        "repeat for several")
    with_defines(p)
    p.add_argument("--out", default=None, help="report folder (default: eval.out or reports/<runs name>)")
    with_quiet(p)
    p.set_defaults(fn=_eval)

    p = with_config(command(sub, "stability", "every method on synthetic edge cases (fireflies, NaN, sizes, ...)"))
    p.add_argument("--out", default=None, help="report folder (default: as eval)")
    with_quiet(p)
    p.set_defaults(fn=_stability)


def _eval(args) -> int:
    from mcdenoise.evaluate.run import run_eval
    from mcdenoise.render.external import parse_defines
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
    from mcdenoise.evaluate.stability import run_stability
    data = run_stability(config(args), out=args.out, quiet=args.quiet)
    failed = sum(c["status"] not in ("ok", "not available") for r in data["results"].values() for c in r.values())
    return 1 if failed else 0



# ---- the store and the config: inspect, config, verify -----------------------------------------------------


def _core_commands(sub) -> None:
    """The core's subcommands: store tools and the config."""
    p = command(sub, "inspect", "describe a store (frames, channels, constants, timings, NaN/Inf)")
    p.add_argument("store", help="the store's folder (e.g. data/default; `config` prints a config's)")
    p.add_argument("--frame", default=None, help="SCENE/FRAME, e.g. s00000/000: details of one frame")
    p.add_argument("--json", action="store_true", help="the report as JSON")
    p.set_defaults(fn=_inspect)

    p = with_config(command(sub, "config", "print the resolved config, or --doc the key reference"))
    p.add_argument("--doc", action="store_true", help="print every key with its type, default and meaning (Markdown)")
    p.set_defaults(fn=_config)

    p = command(sub, "verify", "check every file of a store (readable, channels, shapes, checksums, "
                                      "manifests, gt_clean hashes, leftover .tmp); exit 1 on any problem")
    p.add_argument("store", help="the store's folder")
    p.add_argument("--headers-only", action="store_true", help="skip pixel data and checksums (fast)")
    p.add_argument("--jobs", type=int, default=1, help="check scenes in this many processes")
    with_quiet(p, "only the summary line")
    p.add_argument("--bytes", type=int, default=0, metavar="N",
                   help="instead of checking: bytes per channel group of N frames, as stored and re-encoded compact")
    p.add_argument("--encodings", type=int, default=0, metavar="N",
                   help="instead of checking: bytes, write and read seconds per frame of each encoding on N frames")
    p.set_defaults(fn=_verify)


def _inspect(args) -> int:
    from mcdenoise.pipeline.inspect import format_report, inspect_store
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
    from mcdenoise.pipeline.verify import bytes_table, encodings_table, measure_bytes, measure_encodings, run_verify
    if args.encodings:
        print(encodings_table(measure_encodings(args.store, args.encodings)))
        return 0
    if args.bytes:
        print(bytes_table(measure_bytes(args.store, args.bytes)))
        return 0
    return run_verify(args.store, quiet=args.quiet, pixels=not args.headers_only, jobs=args.jobs)


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
