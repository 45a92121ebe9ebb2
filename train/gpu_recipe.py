"""The GPU recipe: one short run on a lent GPU machine that trains the shipped model further and times it.

Prepared here (``python -m pipeline gpu-prepare --config configs/ship.yaml``, CPU): ``.gpu/`` holds
the wheels the bare machine lacks (``pip download`` for its Python) and two crop packs cut from the
training packs (``train.pack``: model-space float16, the first estimate already in them, since OIDN
does not travel). Run there, as one command of the device tool (``carry: [".gpu"]``)::

    bash train/gpu_recipe.sh                  # MINUTES=6 OUT=$OUT by default

which installs the wheels and runs ``python -m mcdenoise gpu-recipe`` (``run``; ``train.commands``
declares its flags): it loads ``train/shipped`` (or ``--model``), trains base and Control Module on
the carried crops for ``--minutes`` (bf16 autocast, the shipped model's formulation and objective,
the same loop as ``make train``), scores the 1-step output against the crops' first estimate on
the carried validation crops, times the network at 256² and 1920×1080 for 1, 4, 9 and 27 steps,
and writes into ``--out`` at most 8 files under 16 MiB:
``base_fp16.safetensors``, ``control_fp16.safetensors`` (the trained weights, float16 for the
trip), ``model.json``, ``report.md``, ``result.json``, ``loss.png``. ``--device cpu --minutes
0.02`` is the dry run the tests do.

A shipped model on OIDN's network (``diffusion.base: oidn``, ``train.oidn_refine``) takes the same
command: ``gpu-prepare`` then cuts crops of the config's OIDN packs (``oidn_{train,val}_crops``),
OIDN's weights travel as the model's own ``base.tza`` (pyoidn stays behind), and ``run_refine``
continues its Control Module with ``RefineTask`` on those crops (the run ``make train`` does) and
times 1 and 3 steps.
"""
from __future__ import annotations

import dataclasses
import json
import platform
import tempfile
import time
from pathlib import Path

import torch

from mcdenoise.pipeline.checkpoint import save_safetensors
from mcdenoise.pipeline.config import LOSS_NORMS, PAPER_STEPS
from mcdenoise.pipeline.runs import pick_device
from mcdenoise.pipeline.timing import best_time

from .model import SHIPPED_MODEL, formulation, load
from .pack import PackPairs
from .sampler import sample_tiled
from .train import Job, autocast_dtype, fit

STEPS = (1, 4, 9, PAPER_STEPS)
SIZES = {"256x256": (256, 256), "1920x1080": (1080, 1920)}


@dataclasses.dataclass(frozen=True)
class Settings:
    """One run of the recipe: the flags of ``python -m pipeline gpu-recipe`` (defaults and help there)."""
    out: str                 # the output folder (at most 8 files under 16 MiB)
    model: str | None        # the model folder to train further; None: the shipped model
    train: str               # the carried crop packs (gpu-prepare)
    val: str
    minutes: float           # training time budget
    batch: int
    lr: float
    device: str
    loss_norm: str           # diffusion.loss_norm of the training
    sizes: str               # bench frame sizes, WxH comma-separated
    oidn_train: str          # a model on OIDN's network: its crop packs
    oidn_val: str


def _validator(model, val: PackPairs, form, device, autocast):
    from mcdenoise.pipeline.metrics import psnr

    from .data import from_model

    items = [val[i] for i in range(len(val))]

    def validate(m) -> dict:
        m.eval()
        scores = {"psnr": [], "estimate_psnr": [], "noisy_psnr": []}
        with torch.no_grad():
            for it in items:
                x = {k: v[None].to(device) for k, v in it.items()}
                y = sample_tiled(m, x["noisy"], x["aux"], image=x["image"], formulation=form, steps=1, seed=0,
                                 autocast_dtype=autocast)[0]
                ref = from_model(it["target"]).numpy()
                for key, img in (("psnr", y[0].float().cpu()), ("estimate_psnr", it["image"]), ("noisy_psnr", it["noisy"])):
                    scores[key].append(min(psnr(from_model(img).numpy(), ref), 999.0))
        m.train()
        return {k: float(sum(v) / len(v)) for k, v in scores.items()} | {"frames": len(items)}
    return validate


def bench(model, form, device, autocast, aux_channels: int, sizes: dict | None = None) -> list[dict]:
    """Network seconds per frame (the first estimate excluded: it runs on the CPU, OIDN does not travel)."""
    rows = []
    for name, (h, w) in (sizes or SIZES).items():
        g = torch.Generator().manual_seed(0)
        noisy = (torch.rand(1, 3, h, w, generator=g) * 2 - 1).to(device)
        aux = torch.rand(1, aux_channels, h, w, generator=g).to(device)
        for steps in STEPS:
            def run():
                sample_tiled(model, noisy, aux, image=noisy, formulation=form, steps=steps, seed=0,
                             autocast_dtype=autocast)
                if device.type == "cuda":
                    torch.cuda.synchronize()
            run()   # warm-up (kernels, cudnn autotune)
            rows.append({"size": name, "steps": steps, "seconds": round(best_time(run, 2), 4)})
    return rows


def run_refine(args: Settings, sizes: dict) -> int:
    """The recipe for a model on OIDN's network (``diffusion.base: oidn``): its own training run
    (``train.oidn_refine.RefineTask``, the shipped model's settings) on the carried OIDN crop packs, from
    the shipped base and Control Module; the trained Control Module and the timings into ``--out``."""
    from mcdenoise.pipeline.config import load_config
    from mcdenoise.pipeline.fit import fit as fit_task

    from . import oidn_refine

    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = json.loads((Path(args.model) / "model.json").read_text())
    st = meta.get("settings", {})
    side = int(oidn_refine.load_pack(Path(args.oidn_train))["x"].shape[-1])
    keys = ("weight_decay", "grad_clip", "ema", "hdr_weight", "dropout")
    cfg = load_config(None, [f"diffusion.{k}={st[k]}" for k in keys if k in st] + [
        "diffusion.base=oidn", f"diffusion.crop={side}", f"diffusion.batch_size={args.batch}",
        f"diffusion.lr={args.lr}", "diffusion.epochs=10000", "diffusion.warmup_steps=20", "diffusion.crops_per_frame=1",
        f"diffusion.time_budget_s={args.minutes * 60}", f"diffusion.device={args.device}",
        f"diffusion.residual_scale={meta['formulation']['residual_scale']}",
        f"diffusion.train_steps={st.get('train_steps', [1])}", f"diffusion.t_focus={meta['formulation']['t_focus']}"])
    work = Path(tempfile.mkdtemp(prefix="gpu_recipe_")) / "diffusion_gpu"
    task = oidn_refine.RefineTask(cfg, "any", quiet=True, folder=work, init=Path(args.model),
                                  source=oidn_refine.PackSource(Path(args.oidn_train), Path(args.oidn_val)))
    summary = fit_task(task, quiet=True)
    hist = json.loads((work / "train.json").read_text())["history"]
    trained = [h for h in hist if h["epoch"] > 0]
    seconds = hist[-1]["seconds"] if trained else 0.0
    images = len(trained) * task.steps_per_epoch * args.batch
    model = task.model.eval()
    save_safetensors(out / "control_fp16.safetensors", {k: v.half().contiguous().cpu()
                                                        for k, v in model.control.state_dict().items()},
                     {"format": oidn_refine.FORMAT})
    (out / "model.json").write_text(json.dumps(meta, indent=1))
    if (work / "loss.png").exists():
        (out / "loss.png").write_bytes((work / "loss.png").read_bytes())
    rows = []
    for name, (h, w) in sizes.items():
        g = torch.Generator().manual_seed(0)
        x = torch.rand(1, 9, h + (-h % 16), w + (-w % 16), generator=g).to(task.device)
        cond = torch.rand(1, model.cond_channels, *x.shape[-2:], generator=g).to(task.device)
        for steps in (1, 3):
            def go():
                oidn_refine.sample(model, x, cond, task.form, steps=steps)
                if task.device.type == "cuda":
                    torch.cuda.synchronize()
            go()
            rows.append({"size": name, "steps": steps, "seconds": round(best_time(go, 2), 4)})
    result = {"device": str(task.device), "gpu": torch.cuda.get_device_name(0) if task.device.type == "cuda" else None,
              "platform": platform.platform(), "torch": torch.__version__, "minutes": args.minutes,
              "epochs": len(trained), "train_seconds": seconds, "train_images": images,
              "train_images_per_s": round(images / seconds, 1) if seconds else None,
              "history": [{**h, "val": {"psnr": h["val"]["psnr"], "estimate_psnr": h["val"]["estimate_psnr"]}}
                          for h in hist if h.get("val")], "bench": rows, "summary": summary["line"],
              "wall_seconds": round(time.perf_counter() - t0, 1)}
    (out / "result.json").write_text(json.dumps(result, indent=1, default=str))
    (out / "report.md").write_text(report(result))
    print(report(result), flush=True)
    return 0


def run(settings: Settings) -> int:
    """The recipe: ``run_refine`` for a model on OIDN's network, else ``run_diffusion``; exit status 0."""
    from .oidn_refine import FORMAT as REFINE

    args = dataclasses.replace(settings, model=settings.model or str(SHIPPED_MODEL))
    sizes = {t: (int(t.split("x")[1]), int(t.split("x")[0])) for t in args.sizes.split(",")}
    if json.loads((Path(args.model) / "model.json").read_text()).get("format") == REFINE:
        return run_refine(args, sizes)
    return run_diffusion(args, sizes)


def run_diffusion(args: Settings, sizes: dict) -> int:
    """The recipe for a model on the IF-II-layout diffusion base: base and Control Module trained
    further on the carried crop packs, the weights and the timings into ``--out``."""
    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    device = pick_device(args.device)
    model, meta = load(args.model, device)
    form = dataclasses.replace(formulation(meta), loss_norm=args.loss_norm)
    model.train_base = True
    model.base.requires_grad_(True)
    autocast = autocast_dtype("auto", device)
    side = int(PackPairs(Path(args.train), crop=None, estimate=form.estimate).t["noisy"].shape[-1])
    train = PackPairs(Path(args.train), crop=side, estimate=form.estimate)   # a crop of the whole: flips only
    val = PackPairs(Path(args.val), crop=None, estimate=form.estimate)
    work = Path(tempfile.mkdtemp(prefix="gpu_recipe_"))
    trainable = torch.nn.ModuleDict({"control": model.control, "base": model.base})
    job = Job(name="gpu", folder=work, model=model, trainable=trainable, params=model.trainable_parameters(),
              train_ds=train, validate=_validator(model, val, form, device, autocast), save_best=lambda r: None,
              epochs=10_000, batch_size=args.batch, lr=args.lr, weight_decay=0.01, warmup_steps=20, grad_clip=1.0,
              nan_limit=10, time_budget_s=args.minutes * 60, seed=0, fingerprint={"gpu": 1}, device=device,
              autocast=autocast, objective=form.objective([1, 3, 9]), validate_initial=True)
    summary = fit(job, quiet=True)
    hist = json.loads((work / "train.json").read_text())["history"]
    trained = [h for h in hist if h["epoch"] > 0]
    seconds = hist[-1]["seconds"] if trained else 0.0
    images = len(trained) * (len(train) // args.batch) * args.batch
    save_safetensors(out / "base_fp16.safetensors", {k: v.half().contiguous().cpu()
                                                     for k, v in model.base.state_dict().items()}, {"format": "pt"})
    save_safetensors(out / "control_fp16.safetensors", {f"control.{k}": v.half().contiguous().cpu()
                                                        for k, v in model.control.state_dict().items()},
                     {"format": "mcdenoise-control"})
    (out / "model.json").write_text(json.dumps(meta, indent=1))
    if (work / "loss.png").exists():
        (out / "loss.png").write_bytes((work / "loss.png").read_bytes())
    result = {"device": str(device), "gpu": torch.cuda.get_device_name(0) if device.type == "cuda" else None,
              "platform": platform.platform(), "torch": torch.__version__, "minutes": args.minutes,
              "epochs": len(trained), "train_seconds": seconds, "train_images": images,
              "train_images_per_s": round(images / seconds, 1) if seconds else None, "history": hist,
              "bench": bench(model.eval(), form, device, autocast, model.control.aux_channels, sizes),
              "summary": summary["line"], "wall_seconds": round(time.perf_counter() - t0, 1)}
    (out / "result.json").write_text(json.dumps(result, indent=1, default=str))
    (out / "report.md").write_text(report(result))
    print(report(result), flush=True)
    return 0


def report(r: dict) -> str:
    first, last = r["history"][0]["val"], r["history"][-1]["val"]
    first.setdefault("estimate_psnr", first.get("psnr"))
    lines = [f"# GPU recipe: {r['gpu'] or r['device']}", "",
             f"{r['epochs']} epochs in {r['train_seconds']} s, {r['train_images_per_s']} training crops/s; "
             f"validation (1 step): {first['psnr']:.2f} dB before, {last['psnr']:.2f} dB after "
             f"(first estimate {first['estimate_psnr']:.2f} dB).", "",
             "| frame | steps | network seconds |", "| --- | --- | --- |"]
    lines += [f"| {b['size']} | {b['steps']} | {b['seconds']} |" for b in r["bench"]]
    return "\n".join(lines) + "\n"


# ---- preparation, on this machine ------------------------------------------------------------------

WHEELS = ("diffusers==0.42.1", "huggingface_hub==2.4.0", "safetensors==0.8.0", "regex==2026.11.15",
          "OpenEXR==3.5.3", "PyYAML==6.0.3", "tqdm==4.70.1", "filelock==4.2.11", "fsspec==2026.9.0",
          "importlib_metadata==10.2.0", "zipp==4.1.2", "packaging==26.3", "typing_extensions==4.16.0")


def crop_pack(src: Path, dest: Path, count: int, side: int, seed: int = 0) -> int:
    """``count`` random ``side``² crops of a training pack's items, as a pack of their own (each crop its
    own frame); returns the bytes written."""
    import numpy as np
    from safetensors.torch import load_file

    from .pack import FORMAT, read_header

    header, t = read_header(src), load_file(str(src))
    rng = np.random.default_rng(seed)
    n, H, W = t["noisy"].shape[0], t["noisy"].shape[-2], t["noisy"].shape[-1]
    picks = [(int(rng.integers(n)), int(rng.integers(H - side + 1)), int(rng.integers(W - side + 1)))
             for _ in range(count)]
    cut = lambda a, i, y, x: a[i, :, y:y + side, x:x + side]  # noqa: E731
    out = {name: torch.stack([cut(t[name], i, y, x) for i, y, x in picks]).contiguous()
           for name in ("noisy", "aux", "image")}
    out["target"] = torch.stack([cut(t["target"], int(t["frame"][i]), y, x) for i, y, x in picks]).contiguous()
    out["frame"] = torch.arange(count, dtype=torch.int32)
    out["spp"] = torch.stack([t["spp"][i] for i, _, _ in picks]).to(torch.int32)
    header = {**header, "frames": [f"crop{k}" for k in range(count)], "crops_of": str(src)}
    dest.parent.mkdir(parents=True, exist_ok=True)
    save_safetensors(dest, out, {"format": FORMAT, "header": json.dumps(header)})
    return dest.stat().st_size


def prepare(cfg, out: Path = Path(".gpu"), train_crops: int = 48, val_crops: int = 12, side: int = 48,
            wheels: bool = True, python: str = "3.12") -> None:
    """Write ``out``: crop packs from the config's training packs and the wheels the GPU machine lacks."""

    from .model import estimator
    from .oidn_refine import is_oidn_base
    from .pack import pack_path

    if is_oidn_base(cfg):
        _prepare_oidn(cfg, out, train_crops, val_crops, side)
        if wheels:
            _wheels(out, python)
        return
    kind = estimator(cfg).kind
    for split, count in (("train", train_crops), ("val", val_crops)):
        src = pack_path(cfg.runs, split, kind)
        if not src.exists():
            raise SystemExit(f"{src}: no pack; run `python -m pipeline pack --config ...` first")
        size = crop_pack(src, out / f"{split}_crops.safetensors", count, side, seed=1 if split == "val" else 0)
        print(f"{out / f'{split}_crops.safetensors'}: {count} crops of {side}², {size / 2**20:.1f} MiB", flush=True)
    if wheels:
        _wheels(out, python)


def _wheels(out: Path, python: str) -> None:
    import subprocess
    import sys
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--python-version", python,
           "--platform", "manylinux2014_x86_64", "--platform", "manylinux_2_17_x86_64", "--platform",
           "manylinux_2_28_x86_64", "-d", str(out / "wheels"), *WHEELS]
    subprocess.run(cmd, check=True)


def _prepare_oidn(cfg, out: Path, train_crops: int, val_crops: int, side: int) -> None:
    """Crops of the config's OIDN packs (train and val splits; built if missing) for the OIDN-based model."""
    from mcdenoise.pipeline.store import Store

    from .oidn_pack import crop_pack, ensure_pack, load_pack, pack_path
    from .oidn_refine import StoreSource

    src = StoreSource(cfg)
    store = Store(cfg.store)
    for split, keys, count in (("train", src.train_keys, train_crops), ("val", src.val_keys, val_crops)):
        pack = load_pack(ensure_pack(store, keys, pack_path(cfg.runs, split)))
        dest = out / f"oidn_{split}_crops.safetensors"
        out.mkdir(parents=True, exist_ok=True)
        size = crop_pack(pack, dest, count, side, seed=1 if split == "val" else 0)
        print(f"{dest}: {count} crops of {side}², {size / 2**20:.1f} MiB", flush=True)
