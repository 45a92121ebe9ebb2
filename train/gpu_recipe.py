"""The GPU recipe: one short run on a lent GPU machine that trains the shipped model further and times it.

Prepared here (``python -m pipeline gpu-prepare --config configs/ship.yaml``, CPU): ``.gpu/`` holds
the wheels the bare machine lacks (``pip download`` for its Python) and two crop packs cut from the
config's OIDN packs (``train.data``: every buffer in OIDN's space, the target beside it). Run
there, as one command of the device tool (``carry: [".gpu"]``)::

    bash train/gpu_recipe.sh                  # MINUTES=6 OUT=$OUT by default

which installs the wheels and runs ``python -m mcdenoise gpu-recipe`` (``run``; ``train.commands``
declares its flags): it loads ``train/shipped`` (or ``--model``: a model on OIDN's network,
``train.model``), whose weights travel as its own ``base.tza`` (pyoidn stays behind), continues
its Control Module with ``RefineTask`` on the carried crops for ``--minutes`` (the run ``make train``
does, bf16 autocast on the GPU), times 1 and 3 steps at 256² and 1920×1080, and writes into ``--out``
at most 8 files under 16 MiB: ``control_fp16.safetensors`` (the trained Control Module, float16 for
the trip), ``model.json``, ``report.md``, ``result.json``, ``loss.png``. ``--device cpu --minutes
0.02`` is the dry run the tests do.
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
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.timing import best_time

from .model import SHIPPED_MODEL


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
    sizes: str               # bench frame sizes, WxH comma-separated


def run_refine(args: Settings, sizes: dict) -> int:
    """The recipe for a model on OIDN's network (``diffusion.base: oidn``): its own training run
    (``train.train.RefineTask``, the shipped model's settings) on the carried OIDN crop packs, from
    the shipped base and Control Module; the trained Control Module and the timings into ``--out``."""
    from mcdenoise.pipeline.config import load_config
    from mcdenoise.pipeline.fit import fit as fit_task

    from .data import PackSource, load_pack
    from .model import FORMAT
    from .sampler import sample
    from .train import RefineTask

    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = json.loads((Path(args.model) / "model.json").read_text())
    check_crops(Path(args.train), Path(args.model), meta)
    st = meta.get("settings", {})
    side = int(load_pack(Path(args.train))["x"].shape[-1])
    keys = ("weight_decay", "grad_clip", "ema", "hdr_weight", "dropout")
    cfg = load_config(None, [f"diffusion.{k}={st[k]}" for k in keys if k in st] + [
        "diffusion.base=oidn", f"diffusion.crop={side}", f"diffusion.batch_size={args.batch}",
        f"diffusion.lr={args.lr}", "diffusion.epochs=10000", "diffusion.warmup_steps=20", "diffusion.crops_per_frame=1",
        f"diffusion.time_budget_s={args.minutes * 60}", f"diffusion.device={args.device}"])
    work = Path(tempfile.mkdtemp(prefix="gpu_recipe_")) / "diffusion_gpu"
    task = RefineTask(cfg, "any", quiet=True, folder=work, init=Path(args.model),
                                  source=PackSource(Path(args.train), Path(args.val)))
    summary = fit_task(task, quiet=True)
    hist = json.loads((work / "train.json").read_text())["history"]
    trained = [h for h in hist if h["epoch"] > 0]
    seconds = hist[-1]["seconds"] if trained else 0.0
    images = len(trained) * task.steps_per_epoch * args.batch
    model = task.model.eval()
    save_safetensors(out / "control_fp16.safetensors", {k: v.half().contiguous().cpu()
                                                        for k, v in model.control.state_dict().items()},
                     {"format": FORMAT})
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
                sample(model, x, cond, task.form, steps=steps)
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


def check_crops(crops: Path, model: Path, meta: dict) -> None:
    """TrainError unless the crops' albedo and normal are what the model's base reads (prefiltered for a
    ``_calb_cnrm`` network, as rendered otherwise)."""
    from .data import pack_clean_aux
    from .model import NETWORK, clean_aux

    want, kind = clean_aux(meta), lambda clean: "prefiltered" if clean else "rendered"
    if pack_clean_aux(crops) != want:
        raise TrainError(f"{crops}: crops with {kind(not want)} albedo and normal, but the model {model} (base "
                         f"{meta.get('base_network', NETWORK)}) reads {kind(want)} ones; cut them for "
                         f"it: python -m pipeline gpu-prepare --model {model} --config …")


def run(settings: Settings) -> int:
    """The recipe (``run_refine``) on ``settings.model`` (default: the shipped model); exit status 0."""
    from mcdenoise.pipeline import weights

    args = dataclasses.replace(settings, model=settings.model or str(SHIPPED_MODEL))
    sizes = {t: (int(t.split("x")[1]), int(t.split("x")[0])) for t in args.sizes.split(",")}
    weights.read_record(Path(args.model), "oidn_control", "the GPU recipe continues a model on OIDN's network; "
                        "train another model with `make train` on the GPU machine")
    return run_refine(args, sizes)


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


def prepare(cfg, out: Path = Path(".gpu"), train_crops: int = 48, val_crops: int = 12, side: int = 48,
            wheels: bool = True, python: str = "3.12", model: Path | None = None) -> None:
    """Write ``out``: crop packs from the config's training packs, with albedo and normal as the base of
    ``model`` (default: the shipped model, which the recipe trains) reads them, and the wheels the GPU
    machine lacks."""
    from mcdenoise.pipeline import weights

    from .model import NETWORK

    model = Path(model or SHIPPED_MODEL)
    network = weights.read_record(model, "oidn_control", "gpu-prepare cuts crops for a model on OIDN's network "
                                  "(--model)").get("base_network", NETWORK)
    _prepare_oidn(cfg, out, train_crops, val_crops, side, network)
    if wheels:
        _wheels(out, python)


def _wheels(out: Path, python: str) -> None:
    import subprocess
    import sys
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--python-version", python,
           "--platform", "manylinux2014_x86_64", "--platform", "manylinux_2_17_x86_64", "--platform",
           "manylinux_2_28_x86_64", "-d", str(out / "wheels"), *WHEELS]
    subprocess.run(cmd, check=True)


def _prepare_oidn(cfg, out: Path, train_crops: int, val_crops: int, side: int, network: str) -> None:
    """Crops of the config's OIDN packs (train and val splits; built if missing) for a model on OIDN's
    ``network``; the train crops come from the train pack the CPU run reads (``diffusion.extra_stores``
    included)."""
    from .data import StoreSource, crop_pack, ensure_pack, load_pack

    src = StoreSource(cfg, network)
    for split, count in (("train", train_crops), ("val", val_crops)):
        pack = (src.train_pack(True) if split == "train"
                else load_pack(ensure_pack(src.store, src.val_keys, src.pack_path("val"), clean_aux=src.clean_aux)))
        dest = out / f"{split}_crops.safetensors"
        out.mkdir(parents=True, exist_ok=True)
        size = crop_pack(pack, dest, count, side, seed=1 if split == "val" else 0, clean_aux=src.clean_aux)
        print(f"{dest}: {count} crops of {side}², {size / 2**20:.1f} MiB", flush=True)
