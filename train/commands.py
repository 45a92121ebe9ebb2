"""The denoisers' subcommands of ``python -m pipeline``: ``train`` (every model: the diffusion denoiser,
oidn_ft, and the Isik and AFGSA baselines), ``export``, ``gpu-prepare``, ``gpu-recipe``, ``gpu-unpack``,
``pack``, ``denoise``, ``afgsa-report`` and ``bench-denoise``.

``add_commands`` declares them (see ``pipeline.commands``); each handler imports what it runs
(``train.cli`` and the trainers load torch, this module does not).
"""
from __future__ import annotations

from pathlib import Path

from mcdenoise.pipeline.commands import config, spp, with_config, with_quiet
from mcdenoise.pipeline.config import ConfigError


def add_commands(sub) -> None:
    """The denoisers' subcommands, in the order of their --help: training, its preparation, export,
    the GPU recipe, packs, inference, then AFGSA's report and the inference benchmark."""
    _training_commands(sub)
    _gpu_commands(sub)
    _inference_commands(sub)
    _report_commands(sub)


def _training_commands(sub) -> None:
    p = with_config(sub.add_parser("train", help="train a denoiser: --model diffusion (ours), oidn_ft (OIDN "
                                                 "fine-tuned), isik or afgsa (baselines); diffusion runs under "
                                                 "torchrun for DDP"))
    p.add_argument("--model", default="diffusion", choices=["diffusion", "oidn_ft", "isik", "afgsa"],
                   help="which denoiser")
    p.add_argument("--spp", type=spp, required=True,
                   help="sample count of the noisy input (4, 16, 64), or 'any': one diffusion or AFGSA model "
                        "for all")
    with_quiet(p)
    p.set_defaults(fn=_train)

    p = with_config(sub.add_parser("export", help="copy a trained diffusion run into a self-contained model folder "
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


def _gpu_commands(sub) -> None:
    p = sub.add_parser("gpu-prepare", help="write .gpu/ for the GPU recipe: the packages a lent GPU machine's image "
                                           "lacks (train/gpu_image.txt) and OIDN's aux networks")
    p.add_argument("--out", default=".gpu")
    p.add_argument("--python", default="3.12", help="the machine's Python version (the wheels' ABI)")
    p.add_argument("--no-wheels", action="store_true", help="OIDN's aux networks only")
    p.set_defaults(fn=_gpu_prepare)

    p = sub.add_parser("gpu-recipe", help="on a lent GPU machine (bash train/gpu_recipe.sh): render a store, clean it, "
                                          "train the shipped model on it and time denoising, in one run",
                       description="The GPU recipe (train/gpu_recipe.py).")
    p.add_argument("--config", default="configs/ship.yaml", help="the config whose dataset is rendered")
    p.add_argument("--out", required=True, help="the folder of the files that come back (at most 8)")
    p.add_argument("--model", default=None, help="the model to train on (default: train/shipped)")
    p.add_argument("--minutes", type=float, default=9.0, help="the whole run's wall-clock budget")
    p.add_argument("--render-share", type=float, default=0.35, help="of the budget, for rendering")
    p.add_argument("--clean-share", type=float, default=0.08, help="of the budget, for the cleaner's training")
    p.add_argument("--seed", type=int, default=2000, help="the store's seed (other scenes than the shipped model saw)")
    p.add_argument("--device", default="auto", help="auto (CUDA if there is one), cuda or cpu")
    p.add_argument("--workers", type=int, default=12, help="render processes")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--crop", type=int, default=128, help="crop side (at most the frames' side, a multiple of 16)")
    p.add_argument("--lr", type=float, default=2e-4)
    p.add_argument("--loader-workers", type=int, default=8, help="processes cutting training crops")
    p.add_argument("--work", default="/tmp/mcdenoise_gpu", help="where the store and the runs go (emptied first)")
    p.add_argument("overrides", nargs="*", default=[], help="key=value config overrides for every phase")
    p.set_defaults(fn=_gpu_recipe)

    p = sub.add_parser("gpu-unpack", help="the GPU recipe's files as model folders to score: DEST (the best epoch) and "
                                          "DEST/epoch<N> for each of snapshots.safetensors")
    p.add_argument("files", help="what the recipe's --out brought back")
    p.add_argument("dest", help="e.g. train/candidates/gpu")
    p.set_defaults(fn=_gpu_unpack)


def _inference_commands(sub) -> None:
    p = with_config(sub.add_parser("pack", help="decode the store once into compact training packs (train/data.py)"))
    p.add_argument("--split", action="append", default=None, help="split to pack (repeatable; default: train, val)")
    with_quiet(p)
    p.set_defaults(fn=_pack)

    p = with_config(sub.add_parser("denoise", help="denoise a store frame or an EXR with a trained diffusion run"))
    p.add_argument("--spp", type=spp, default=None,
                   help="the input's samples per pixel (and the run diffusion_spp<N>, else diffusion_sppany, else the "
                        "shipped model); required with --frame; with --exr: the EXR header's if it has one, else 16")
    p.add_argument("--frame", default=None, help="SCENE/FRAME of the store, e.g. s00000/000")
    p.add_argument("--exr", default=None, help="an EXR with R,G,B (and optionally our feature layers)")
    p.add_argument("--out", required=True, help="output EXR")
    p.add_argument("--skip", type=int, default=None, help="sampler steps to skip (default: the run's)")
    p.add_argument("--steps", type=int, default=None, help="sampler steps (default: the model's)")
    p.add_argument("--samples", type=int, default=None,
                   help="average K samples; their per-pixel standard deviation goes to the 'std' layer")
    p.add_argument("--seed", type=int, default=None)
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
    p = with_config(sub.add_parser("afgsa-report", help="AFGSA trained against GT_clean vs against GT1, both "
                                                        "scored against GT_clean: table and crop grid"))
    p.add_argument("--spp", type=int, default=4)
    p.add_argument("--out", default="reports/afgsa")
    p.add_argument("--run", action="append", default=None, metavar="LABEL=FOLDER", dest="runs",
                   help="another AFGSA run folder to compare (e.g. the adv_weight=0 ablation); repeatable")
    p.set_defaults(fn=_afgsa_report)

    p = with_config(sub.add_parser("bench-denoise", help="seconds per frame of ours, its base and OIDN's own engine at "
                                                         "256², 1080p (and 4K on CUDA)"))
    p.add_argument("--spp", type=int, default=4, help="use the trained run of this spp when there is one")
    p.add_argument("--sizes", default=None, help="frame sizes WxH, comma-separated (default: 256x256,1920x1080; "
                                                "with CUDA also 3840x2160)")
    p.add_argument("--device", default=None, help="auto, cuda or cpu (default: diffusion.device)")
    p.add_argument("--precision", default="auto", choices=("auto", "fp32", "fp16", "bf16"))
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--out", default="reports/bench")
    p.set_defaults(fn=_bench_denoise)


# ---- handlers: parsed flags -> one call ----------------------------------------------------------


def _train(args) -> int:
    cfg = config(args)
    if args.model == "isik":
        from mcdenoise.clean.cli import cmd_train_isik
        return cmd_train_isik(cfg, args.spp, quiet=args.quiet)
    if args.model == "afgsa":
        from .baselines.afgsa import train as train_afgsa
        train_afgsa(cfg, args.spp, quiet=args.quiet)
        return 0
    if args.model == "oidn_ft":
        from .baselines.oidn_ft import train as train_oidn_ft
        train_oidn_ft(cfg, args.spp, quiet=args.quiet)
        return 0
    from .train import train
    train(cfg, args.spp, quiet=args.quiet)
    return 0


def _export(args) -> int:
    from .export import export, export_oidn, fit_sigma, rebase, set_strength, swap_base
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


def _gpu_prepare(args) -> int:
    import json

    from .gpu_recipe import prepare
    record = prepare(Path(args.out), args.python, wheels=not args.no_wheels)
    print(json.dumps(record, indent=1))
    return 0


def _gpu_recipe(args) -> int:
    import dataclasses

    from .gpu_recipe import Settings, run
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(Settings) if f.name != "overrides"}
    return run(Settings(**values, overrides=tuple(args.overrides)))


def _gpu_unpack(args) -> int:
    from .gpu_recipe import unpack
    for folder in unpack(Path(args.files), Path(args.dest)):
        print(folder)
    return 0


def _pack(args) -> int:
    from .data import cmd_pack
    return cmd_pack(config(args), args.split or ["train", "val"], quiet=args.quiet)


def _denoise(args) -> int:
    from .infer import cmd_denoise, cmd_denoise_oidn
    if args.method != "ours" or args.oidn_weights:
        return cmd_denoise_oidn(config(args), args.frame, args.exr, args.out, args.method, args.oidn_weights,
                                spp=args.spp, quiet=args.quiet, ensemble=args.ensemble)
    return cmd_denoise(config(args), args.spp, args.frame, args.exr, args.out, args.skip, args.seed,
                       base_only=args.base_only, quiet=args.quiet, steps=args.steps, samples=args.samples,
                       ensemble=args.ensemble, strength=args.strength, device=args.device, precision=args.precision)


def _afgsa_report(args) -> int:
    from .baselines.afgsa_report import default_runs, run_afgsa_report
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
    from .bench import parse_sizes, run
    if args.sizes:
        try:
            parse_sizes(args.sizes)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    run(config(args), spp=args.spp, sizes=args.sizes, device=args.device, precision=args.precision,
        repeats=args.repeats, out=args.out)
    return 0
