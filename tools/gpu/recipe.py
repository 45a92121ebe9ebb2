"""The GPU recipe: render, clean, train and time the shipped kind of model on one lent GPU machine, in one run.

A lent machine (an H200 here) lives minutes and starts bare: nothing can be fetched there and at most
64 MiB travel with the source tree. Prepared here (``python tools/gpu/recipe.py prepare``, CPU), ``.gpu/``
holds what the machine's image lacks (``tools/gpu/image.txt`` lists what it has): the packages as one
``site.tar.xz`` (Mitsuba cut to the variants and plugins the renderer uses) and OIDN's aux networks
(``oidn/*.tza``: pyoidn does not travel; ``train.oidn`` runs them in PyTorch). There, as one
command of the device tool (``carry: [".gpu"]``)::

    bash tools/gpu/recipe.sh                      # CONFIG=configs/ship.yaml MINUTES=9 OUT=$OUT

and on the CPU, the same phases in seconds (the test suite runs this)::

    DEVICE=cpu CONFIG=configs/tiny.yaml MINUTES=0.2 bash tools/gpu/recipe.sh

The phases, each a command a user runs too, each timed; ``report.md`` and ``result.json`` are rewritten
after every phase, so a run cut short still says how far it got:

1. **render** ``pipeline dataset --time-limit``: a new store of the config (``--seed``: other scenes than the
   shipped model's), Mitsuba's CUDA variant, ``executor.workers`` processes; frames not finished at the limit
   are not in the store and every later stage reads complete frames only;
2. **clean** ``pipeline gt-clean``: the cleaner trained there on GT1/GT2 of the new frames;
3. **train** ``pipeline train --model diffusion --spp any``: from the shipped model (``diffusion.init``: its base
   frozen, its Control Module trained on), batch ``--batch`` of ``--crop``² in bf16, validated on the new store's
   val frames after every epoch, the best kept; for the time left;
4. **bench**: ``denoise`` end to end and the networks alone at 256², 1080p and 4K, fp32 and fp16.

Back in ``--out`` (8 files under 16 MiB): a model folder (``control.safetensors`` in float16, ``model.json``,
``base.tza``: the best epoch on the new store's val frames), ``snapshots.safetensors`` (the Control Modules of up to
six epochs 1, 2, 4, 8, … spread over the run: on the ship data the val frames' best is not the best on scenes unlike
them, docs/diffusion.md), ``report.md``, ``result.json`` (every timing, the validation curve against megapixels
trained), ``loss.png`` and ``logs.txt``. ``python tools/gpu/recipe.py unpack FILES train/candidates/<name>`` turns
them into model folders to score.

This is a tool of the checkout, not of the installed package: run as a script from anywhere, it puts the
repository root first on ``sys.path`` and runs the phases (``python -m pipeline ...``) from there. Its commands:
``prepare``, ``run`` (what ``recipe.sh`` starts) and ``unpack`` (``--help`` for each).
"""
from __future__ import annotations

import argparse
import dataclasses
import io
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tarfile
import time
import zipfile
from pathlib import Path

# The repository root (a checkout has mcdenoise/ there): first on the path, so that the script imports the
# checkout it belongs to; the phases run from there too.
ROOT = Path(__file__).resolve().parents[2]
if sys.path[:1] != [str(ROOT)]:
    sys.path.insert(0, str(ROOT))

from mcdenoise.pipeline.errors import PipelineError, TrainError  # noqa: E402
from mcdenoise.train.model import SHIPPED_MODEL  # noqa: E402

IMAGE = Path(__file__).with_name("image.txt")


@dataclasses.dataclass(frozen=True)
class Settings:
    """One run of the recipe: the flags of ``python tools/gpu/recipe.py run`` (defaults and help there)."""
    config: str
    out: str
    model: str | None        # the model to train on (default: the shipped one)
    minutes: float           # the whole recipe's wall-clock budget
    render_share: float      # of the budget, for rendering
    clean_share: float       # of the budget, for the cleaner's training
    seed: int
    device: str
    workers: int             # render processes
    batch: int
    crop: int
    lr: float
    loader_workers: int
    work: str                # where the store and runs go
    overrides: tuple = ()    # more config overrides for every phase


# ---- on the machine ----------------------------------------------------------------------------------


class Recipe:
    """The phases in order; ``self.result`` is what result.json holds, rewritten after each phase."""

    def __init__(self, s: Settings):
        import torch

        self.s, self.t0 = s, time.perf_counter()
        self.deadline = self.t0 + s.minutes * 60
        self.cuda = s.device == "cuda" or (s.device == "auto" and torch.cuda.is_available())
        self.out, self.work = Path(s.out), Path(s.work)
        self.out.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(self.work, ignore_errors=True)
        self.model = Path(s.model or SHIPPED_MODEL)
        self.meta = json.loads((self.model / "model.json").read_text())
        self.log = self.out / "logs.txt"
        self.log.write_text("")
        self.common = [f"store={self.work / 'store'}", f"runs={self.work / 'runs'}", f"seed={s.seed}", *s.overrides]
        self.result: dict = {
            "machine": machine_text(torch), "torch": torch.__version__, "python": platform.python_version(),
            "config": s.config, "seed": s.seed, "model": str(self.model), "budget_s": s.minutes * 60,
            "settings": {k: v for k, v in dataclasses.asdict(s).items() if k not in ("out", "work")}, "phases": {}}

    def left(self) -> float:
        return self.deadline - time.perf_counter()

    def command(self, name: str, args: list, timeout: float | None = None) -> dict:
        """Run ``python -m pipeline ARGS`` with the output appended to logs.txt; its time and last line."""
        cmd = [sys.executable, "-m", "pipeline", *map(str, args)]
        t = time.perf_counter()
        with open(self.log, "a") as fh:
            fh.write(f"$ {' '.join(cmd[1:])}\n")
            fh.flush()
            start = fh.tell()
            proc = subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
            try:
                rc = proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGTERM)    # a training run keeps its best epoch on disk
                rc = proc.wait()
                fh.write(f"(stopped after {timeout:.0f} s)\n")
        with open(self.log) as fh:
            fh.seek(start)
            lines = [x.split("\r")[-1] for x in fh.read().splitlines()]
        last = next((x for x in reversed(lines) if x.strip()), "")
        entry = {"seconds": round(time.perf_counter() - t, 1), "rc": rc, "last": last[-400:]}
        self.result["phases"][name] = entry
        self.write()
        if rc not in (0, -signal.SIGTERM):
            raise TrainError(f"gpu recipe: {name} failed (exit {rc}): {last}; the whole output is in {self.log}")
        return entry

    def render(self) -> None:
        s = self.s
        limit = max(1.0, s.minutes * 60 * s.render_share)
        variant = ["render.variant=cuda_ad_rgb"] if self.cuda else []
        # the val split whole (the yardstick), then the train split for the time left; the test split is not rendered
        common = ["--config", s.config, "--quiet", f"executor.workers={s.workers}", *variant, *self.common]
        val = self.command("render_val", ["dataset", "--splits", "val", *common])
        self.command("render", ["dataset", "--splits", "train", "--time-limit", round(max(1.0, limit - val["seconds"]), 1),
                                *common])
        self.result["phases"]["render"]["seconds"] = round(val["seconds"] + self.result["phases"]["render"]["seconds"], 1)
        from mcdenoise.pipeline.store import Store
        store = Store(self.work / "store")
        done = [k for k in store.frames() if store.frame_record(k.scene, k.frame)]
        records = [store.frame_record(k.scene, k.frame) for k in done]
        entry = self.result["phases"]["render"]
        entry.update(frames=len(done), samples=sum(r["samples"] for r in records),
                     splits={sp: len([k for k in store.frames(sp) if store.frame_record(k.scene, k.frame)])
                             for sp in ("train", "val", "test")})
        entry["frames_per_s"] = round(entry["frames"] / entry["seconds"], 3)
        entry["msamples_per_s"] = round(entry["samples"] / entry["seconds"] / 1e6, 2)
        entry["compile_s_per_frame"], entry["render_s_per_frame"] = frame_shares(records)
        if not entry["splits"]["train"] or not entry["splits"]["val"]:
            raise TrainError(f"gpu recipe: {entry['frames']} frames rendered in {limit:.0f} s, too few for a train and "
                             "a val split; give the recipe more minutes")
        self.write()

    def clean(self) -> None:
        s = self.s
        dev = "cuda" if self.cuda else "cpu"
        self.command("clean", ["gt-clean", "--config", s.config, f"clean.time_budget_s={s.minutes * 60 * s.clean_share:.1f}",
                               f"clean.device={dev}", *self.common])

    def train(self) -> None:
        s = self.s
        bench_s = 60.0 if self.cuda else 5.0
        budget = max(1.0, self.left() - bench_s)
        dev = "cuda" if self.cuda else "cpu"
        net = self.meta.get("base_network", "rt_hdr_calb_cnrm_large")
        args = ["train", "--model", "diffusion", "--spp", "any", "--config", s.config, "--quiet",
                f"diffusion.init={self.model}", "diffusion.base=oidn", f"diffusion.base_network={net}",
                f"diffusion.batch_size={s.batch}", f"diffusion.crop={self.crop()}", f"diffusion.lr={s.lr}",
                "diffusion.epoch_steps=50", "diffusion.crops_per_frame=64", "diffusion.epochs=100000",
                "diffusion.warmup_steps=50", f"diffusion.device={dev}", f"diffusion.loader_workers={s.loader_workers}",
                f"diffusion.keep_epochs=[{','.join(map(str, KEEP_EPOCHS))}]",
                # the time limit of the run itself leaves room to pack the frames and to save the best
                f"diffusion.time_budget_s={max(1.0, budget * 0.85):.1f}", "diffusion.name=gpu", *self.common]
        # On a lease the run is stopped at its budget (its best epoch is on disk); the CPU's dry run goes on until
        # its first epoch is done, whatever the budget.
        self.command("train", args, timeout=budget + 30 if self.cuda else None)
        run = self.work / "runs" / "diffusion_sppany_gpu"
        hist = json.loads((run / "train.json").read_text())
        mpix = s.batch * self.crop() ** 2 / 1e6
        steps = 0
        curve = []
        for h in hist["history"]:
            steps += h.get("steps", 0)
            if h.get("val"):
                curve.append({"epoch": h["epoch"], "seconds": h.get("seconds"), "mpix": round(steps * mpix, 3),
                              "val_psnr": round(h["val"]["psnr"], 4),
                              "gain_over_base": round(h["val"]["psnr"] - h["val"]["estimate_psnr"], 4),
                              **{k: round(v, 4) for k, v in h["val"].items() if k.startswith("gain_spp")}})
        entry = self.result["phases"]["train"]
        entry.update(curve=curve, best=hist.get("best") and {"epoch": hist["best"]["epoch"],
                                                             "val_psnr": hist["best"]["val"]["psnr"]},
                     mpix_trained=curve[-1]["mpix"] if curve else 0.0,
                     mpix_per_s=round(curve[-1]["mpix"] / curve[-1]["seconds"], 3) if curve and curve[-1]["seconds"]
                     else None)
        self.pack_model(run)
        entry["snapshots"] = self.pack_snapshots(run, {c["epoch"]: c for c in curve})
        self.write()

    def crop(self) -> int:
        """``--crop``, or the largest multiple of 16 the config's frames hold."""
        from mcdenoise.pipeline.config import load_config
        w, h = load_config(self.s.config, list(self.s.overrides)).dataset.resolution
        return min(self.s.crop, min(w, h) // 16 * 16)

    def pack_model(self, run: Path) -> None:
        """``--out`` as a model folder: the run's best Control Module in float16 (half the bytes back; ``load``
        reads it as float32), its model.json and the frozen base it was trained on."""
        import torch
        from safetensors.torch import load_file

        from mcdenoise.pipeline.weights import save_safetensors
        from mcdenoise.train.model import FORMAT
        control = load_file(str(run / "control.safetensors"))
        save_safetensors(self.out / "control.safetensors",
                         {k: v.to(torch.float16).contiguous() for k, v in control.items()}, {"format": FORMAT})
        shutil.copy(run / "model.json", self.out / "model.json")
        shutil.copy(run / json.loads((run / "model.json").read_text())["base"], self.out / "base.tza")
        if (run / "loss.png").exists():
            shutil.copy(run / "loss.png", self.out / "loss.png")

    def pack_snapshots(self, run: Path, curve: dict) -> list[dict]:
        """``snapshots.safetensors``: the Control Modules of up to SNAPSHOTS kept epochs (``keep_epochs``, spread
        over the run) in float16, keys ``epoch<N>.<name>``, each epoch's model.json in the metadata. The best epoch
        is chosen on the new store's val frames alone; these let the CPU score the run at several lengths on the
        ``val_*`` scenes too (``unpack``)."""
        import torch
        from safetensors.torch import load_file

        from mcdenoise.pipeline.weights import save_safetensors
        from mcdenoise.train.model import FORMAT
        kept = sorted(int(d.name[5:]) for d in run.glob("epoch*") if (d / "control.safetensors").exists())
        chosen = spread(kept, SNAPSHOTS)
        if not chosen:
            return []
        tensors, meta = {}, {"format": FORMAT, "epochs": json.dumps(chosen)}
        for n in chosen:
            for k, v in load_file(str(run / f"epoch{n}" / "control.safetensors")).items():
                tensors[f"epoch{n}.{k}"] = v.to(torch.float16).contiguous()
            meta[f"epoch{n}.model.json"] = (run / f"epoch{n}" / "model.json").read_text()
        save_safetensors(self.out / "snapshots.safetensors", tensors, meta)
        return [{"epoch": n, "mpix": curve.get(n, {}).get("mpix"), "val_psnr": curve.get(n, {}).get("val_psnr")}
                for n in chosen]

    def bench(self) -> None:
        """``bench-denoise``'s timings (train.bench) of the model it started from, on this machine."""
        from mcdenoise.train.bench import GPU_SIZES, measure, parse_sizes
        t = time.perf_counter()
        sizes = parse_sizes(GPU_SIZES) if self.cuda else [(64, 64)]
        try:
            self.result["bench"] = measure(self.model, sizes, "cuda" if self.cuda else "cpu", repeats=3 if self.cuda else 1)
        except Exception as exc:    # noqa: BLE001 - the trained model is already in --out: say why, keep it
            self.result["bench"] = {"error": f"{type(exc).__name__}: {exc}"[:300]}
        self.result["phases"]["bench"] = {"seconds": round(time.perf_counter() - t, 1)}
        self.write()

    def write(self) -> None:
        self.result["wall_s"] = round(time.perf_counter() - self.t0, 1)
        (self.out / "result.json").write_text(json.dumps(self.result, indent=1, default=str))
        (self.out / "report.md").write_text(report(self.result))


def spread(kept: list[int], k: int) -> list[int]:
    """At most ``k`` of the sorted ``kept``, evenly spread over their indices, the first and the last included."""
    if len(kept) <= k:
        return list(kept)
    return sorted({kept[round(i * (len(kept) - 1) / (k - 1))] for i in range(k)})


def unpack(files: Path, dest: Path) -> list[Path]:
    """The model folders of what a run brought back (``files``: its --out): ``dest`` (the best epoch) and
    ``dest/epoch<N>`` for each snapshot, each with the run's base. Returns the folders written."""
    from safetensors import safe_open

    from mcdenoise.pipeline.exr import atomic_write_bytes
    from mcdenoise.pipeline.weights import save_safetensors
    from mcdenoise.train.model import FORMAT, load
    folders = [dest]
    dest.mkdir(parents=True, exist_ok=True)
    for name in ("control.safetensors", "model.json", "base.tza"):
        atomic_write_bytes(dest / name, lambda tmp, name=name: Path(tmp).write_bytes((files / name).read_bytes()))
    snaps = files / "snapshots.safetensors"
    if snaps.exists():
        with safe_open(str(snaps), "pt") as f:
            meta = f.metadata() or {}
            if meta.get("format") != FORMAT:
                raise TrainError(f"{snaps}: format {meta.get('format')!r}, not {FORMAT!r} snapshots")
            for n in json.loads(meta["epochs"]):
                d = dest / f"epoch{n}"
                d.mkdir(exist_ok=True)
                prefix = f"epoch{n}."
                save_safetensors(d / "control.safetensors",
                                 {k[len(prefix):]: f.get_tensor(k) for k in f.keys() if k.startswith(prefix)},
                                 {"format": FORMAT})
                atomic_write_bytes(d / "base.tza", lambda tmp: Path(tmp).write_bytes((dest / "base.tza").read_bytes()))
                atomic_write_bytes(d / "model.json", lambda tmp, n=n: Path(tmp).write_text(meta[f"epoch{n}.model.json"]))
                folders.append(d)
    for d in folders:
        load(d)    # each loads: its base's checksum, its condition layout, every tensor of the Control Module
    return folders


def run(s: Settings) -> int:
    """All phases; exit status 0, or a TrainError naming the phase that failed (result.json says how far it got)."""
    check_packages()
    r = Recipe(s)
    for phase in (r.render, r.clean, r.train, r.bench):
        phase()
    print(report(r.result), flush=True)
    return 0


def check_packages() -> None:
    """One line naming what the machine lacks, before any phase starts."""
    import importlib.util
    missing = [m for m in ("torch", "numpy", "safetensors", "yaml", "tqdm", "mitsuba", "drjit", "OpenEXR", "trimesh",
                           "diffusers", "scipy", "matplotlib")
               if importlib.util.find_spec(m) is None]
    if missing:
        raise TrainError(f"gpu recipe: this machine lacks the Python module(s) {', '.join(missing)}: carry them in "
                         ".gpu/site.tar.xz (python tools/gpu/recipe.py prepare)")


def machine_text(torch) -> str:
    cpu = f"{os.cpu_count()} cores"
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        return f"{p.name} ({p.total_memory / 2**30:.0f} GiB), {cpu}"
    return f"CPU only, {cpu}"


def frame_shares(records: list[dict]) -> tuple[float | None, float | None]:
    """Mean seconds per frame spent outside rendering (Mitsuba's scene build and kernel compilation: the
    first render of a kernel compiles it) and inside it, from the frames' timing records."""
    if not records:
        return None, None
    total = sum(r["timing"]["total"] for r in records) / len(records)
    render = sum(r["timing"]["render"] for r in records) / len(records)
    return round(total - render, 3), round(render, 3)


def report(r: dict) -> str:
    p = r["phases"]
    lines = [f"# GPU recipe on {r['machine']}", "",
             f"Config `{r['config']}` (seed {r['seed']}), model `{r['model']}`, budget {r['budget_s']:.0f} s, "
             f"wall {r.get('wall_s', 0):.0f} s; torch {r['torch']}, Python {r['python']}.", "",
             "| phase | seconds | result |", "| --- | ---: | --- |"]
    for name, e in p.items():
        what = e.get("last", "")
        if name == "render" and "frames" in e:
            what = (f"{e['frames']} frames ({e['splits']}), {e['frames_per_s']} frames/s, {e['msamples_per_s']} M "
                    f"samples/s; per frame {e['compile_s_per_frame']} s outside rendering (build, compile) and "
                    f"{e['render_s_per_frame']} s rendering")
        if name == "train" and "curve" in e:
            what = f"{e['mpix_trained']} Mpix trained, {e['mpix_per_s']} Mpix/s; best {e['best']}"
        lines.append(f"| {name} | {e['seconds']} | {what.replace('|', '/')} |")
    curve = p.get("train", {}).get("curve")
    if curve:
        lines += ["", "Validation (the new store's val frames; epoch 0 is the model it started from):", "",
                  "| epoch | seconds | Mpix trained | val PSNR | gain over base | " +
                  " | ".join(k for k in curve[0] if k.startswith("gain_spp")) + " |",
                  "| ---: | ---: | ---: | ---: | ---: |" + " ---: |" * len([k for k in curve[0] if k.startswith("gain_spp")])]
        step = max(1, len(curve) // 25)
        for c in curve[::step] + ([curve[-1]] if (len(curve) - 1) % step else []):
            lines.append(f"| {c['epoch']} | {c['seconds']} | {c['mpix']} | {c['val_psnr']:.3f} | "
                         f"{c['gain_over_base']:+.3f} | " + " | ".join(f"{v:+.3f}" for k, v in c.items()
                                                                      if k.startswith("gain_spp")) + " |")
    if r.get("bench", {}).get("rows"):
        from mcdenoise.train.bench import markdown
        lines += ["", markdown(r["bench"])]
    elif r.get("bench"):
        lines += ["", f"bench: {r['bench']['error']}"]
    return "\n".join(lines) + "\n"


# Epochs whose Control Module a run keeps (log-spaced: the curve's shape, not its end alone) and how many of them
# come back in snapshots.safetensors (2.35 MB each in float16; a file comes back only under 16 MiB).
KEEP_EPOCHS = tuple(2 ** i for i in range(17))
SNAPSHOTS = 6


# ---- preparation, on this machine ------------------------------------------------------------------

# What the GPU image lacks, as pinned in requirements.lock (the image's own list: image.txt).
CARRIED = ("mitsuba", "drjit", "OpenEXR", "trimesh", "diffusers")
# Mitsuba's variants and plugins the renderer uses; the rest (other variants, volumes, curves,
# polarisation, sun/sky data, spectral tables) stays behind: a 62.6 MB wheel becomes about 13 MB of xz.
MITSUBA_VARIANTS = ("cuda_ad_rgb", "scalar_rgb")
MITSUBA_DROP_PLUGINS = (
    "blendphase", "bsplinecurve", "catmullrom", "constvolume", "ellipsoids", "ellipsoidsmesh", "gridvolume", "hair",
    "heterogeneous", "hg", "homogeneous", "irradiancemeter", "linearcurve", "measured", "measured_polarized",
    "polarizer", "pplastic", "ptracer", "radiancemeter", "rayleigh", "retarder", "sdfgrid", "sggx", "specfilm",
    "stokes", "sunsky", "timed_sunsky", "tabphase", "volpath", "volpathmis", "volume", "batch", "lanczos",
    "principledthin", "blender", "projector", "irregular")


def image_packages() -> set[str]:
    """The normalised names of the Python packages the GPU image has (image.txt)."""
    names = set()
    for line in IMAGE.read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            names.add(normalise(line.split("==")[0]))
    return names


def normalise(name: str) -> str:
    return name.lower().replace("_", "-").replace(".", "-")


def locked_versions() -> dict[str, str]:
    out = {}
    for line in (ROOT / "requirements.lock").read_text().splitlines():
        if "==" in line and not line.startswith("#"):
            name, version = line.split("==")
            out[normalise(name)] = version.strip()
    return out


def check_carried(names=CARRIED) -> list[str]:
    """``name==version`` of what is carried (pinned as requirements.lock pins them); a TrainError if the image
    has one of them already (a second copy of a package breaks the image's own: huggingface_hub did)."""
    have, locked = image_packages(), locked_versions()
    twice = [n for n in names if normalise(n) in have]
    if twice:
        raise TrainError(f"{IMAGE}: the GPU image already has {', '.join(twice)}; do not carry a second copy")
    return [f"{n}=={locked[normalise(n)]}" for n in names]


def keep_member(name: str) -> bool:
    """Whether a file of the carried packages travels (see MITSUBA_VARIANTS / MITSUBA_DROP_PLUGINS)."""
    parts = name.split("/")
    if "__pycache__" in parts or name.endswith(".pyi"):
        return False
    if parts[0] != "mitsuba" or len(parts) < 2:
        return True
    leaf = parts[-1]
    variant = len(parts) == 2 and leaf.endswith(".so") and ("_ad_" in leaf or leaf.startswith("scalar_"))
    if variant:
        return leaf.split(".")[0] in MITSUBA_VARIANTS
    if parts[1] in ("include", "cmake", "pkgconfig", "mitsuba_stubs") or parts[1:3] in (["data", "sunsky"],):
        return False
    if parts[1:3] == ["data", "srgb.coeff"]:
        return False
    if parts[1] == "plugins" and leaf.endswith(".so"):
        return leaf[:-3] not in MITSUBA_DROP_PLUGINS
    return True


def prepare(out: Path = Path(".gpu"), python: str = "3.12", model: Path | None = None, wheels: bool = True) -> dict:
    """Write ``out``: ``site.tar.xz`` (the carried packages for the machine's Python, trimmed), ``oidn/`` (OIDN's
    aux networks) and ``carried.json`` (names, versions, sizes). Returns carried.json's content."""
    from mcdenoise.train import oidn
    from mcdenoise.train.model import AUX_NETWORKS

    out.mkdir(parents=True, exist_ok=True)
    pins = check_carried()
    record: dict = {"packages": pins, "python": python, "files": {}}
    (out / "oidn").mkdir(exist_ok=True)
    for kind, name in AUX_NETWORKS.items():
        dest = out / "oidn" / f"{name}.tza"
        dest.write_bytes(oidn.weights_blob(name))
        record["files"][str(dest.relative_to(out))] = dest.stat().st_size
    if wheels:
        wheel_dir = out / "wheels"
        download(pins, wheel_dir, python)
        tmp = out / ".site.tar.xz.tmp"
        with tarfile.open(tmp, "w:xz", preset=9) as tar:
            for whl in sorted(wheel_dir.glob("*.whl")):
                with zipfile.ZipFile(whl) as z:
                    for info in z.infolist():
                        if info.is_dir() or not keep_member(info.filename):
                            continue
                        data = z.read(info)
                        ti = tarfile.TarInfo(info.filename)
                        ti.size, ti.mode = len(data), 0o755 if info.filename.endswith(".so") else 0o644
                        tar.addfile(ti, io.BytesIO(data))
        tmp.replace(out / "site.tar.xz")
        shutil.rmtree(wheel_dir)
        record["files"]["site.tar.xz"] = (out / "site.tar.xz").stat().st_size
    record["bytes"] = sum(record["files"].values())
    (out / "carried.json").write_text(json.dumps(record, indent=1))
    return record


def download(pins: list[str], dest: Path, python: str) -> None:
    cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "--python-version",
           python, "--implementation", "cp", "-d", str(dest)]
    for tag in ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"):
        cmd += ["--platform", tag]
    subprocess.run(cmd + pins, check=True)


# ---- command line ------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """``prepare`` (here), ``run`` (on the machine: ``bash tools/gpu/recipe.sh``) and ``unpack`` (here again)."""
    parser = argparse.ArgumentParser(prog="python tools/gpu/recipe.py",
                                     description="The GPU recipe: prepare .gpu/ here, run on a lent GPU machine, "
                                                 "unpack what comes back.")
    sub = parser.add_subparsers(dest="command", required=True)

    text = "write .gpu/ for the GPU recipe: the packages a lent GPU machine's image lacks (tools/gpu/image.txt) " \
           "and OIDN's aux networks"
    p = sub.add_parser("prepare", help=text, description=text[0].upper() + text[1:] + ".")
    p.add_argument("--out", default=".gpu", help="the folder to write (carried to the machine as .gpu)")
    p.add_argument("--python", default="3.12", help="the machine's Python version (the wheels' ABI)")
    p.add_argument("--no-wheels", action="store_true", help="OIDN's aux networks only")
    p.set_defaults(fn=_prepare)

    text = "on a lent GPU machine (bash tools/gpu/recipe.sh): render a store, clean it, train the shipped model on " \
           "it and time denoising, in one run"
    p = sub.add_parser("run", help=text, description=text[0].upper() + text[1:] + ".")
    p.add_argument("--config", default="configs/ship.yaml", help="the config whose dataset is rendered")
    p.add_argument("--out", required=True, help="the folder of the files that come back (at most 8)")
    p.add_argument("--model", default=None, help="the model to train on (default: train/shipped)")
    p.add_argument("--minutes", type=float, default=9.0, help="the whole run's wall-clock budget")
    p.add_argument("--render-share", type=float, default=0.35, help="of the budget, for rendering")
    p.add_argument("--clean-share", type=float, default=0.08, help="of the budget, for the cleaner's training")
    p.add_argument("--seed", type=int, default=2000, help="the store's seed (other scenes than the shipped model saw)")
    p.add_argument("--device", default="auto", help="auto (CUDA if there is one), cuda or cpu")
    p.add_argument("--workers", type=int, default=12, help="render processes")
    p.add_argument("--batch", type=int, default=64, help="training crops per step")
    p.add_argument("--crop", type=int, default=128, help="crop side (at most the frames' side, a multiple of 16)")
    p.add_argument("--lr", type=float, default=2e-4, help="the Control Module's learning rate")
    p.add_argument("--loader-workers", type=int, default=8, help="processes cutting training crops")
    p.add_argument("--work", default="/tmp/mcdenoise_gpu", help="where the store and the runs go (emptied first)")
    p.add_argument("overrides", nargs="*", default=[], help="key=value config overrides for every phase")
    p.set_defaults(fn=_run)

    text = "the GPU recipe's files as model folders to score: DEST (the best epoch) and DEST/epoch<N> for each of " \
           "snapshots.safetensors"
    p = sub.add_parser("unpack", help=text, description=text[0].upper() + text[1:] + ".")
    p.add_argument("files", help="what the recipe's --out brought back")
    p.add_argument("dest", help="e.g. train/candidates/gpu")
    p.set_defaults(fn=_unpack)
    return parser


def _prepare(args) -> int:
    print(json.dumps(prepare(Path(args.out), args.python, wheels=not args.no_wheels), indent=1))
    return 0


def _run(args) -> int:
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(Settings) if f.name != "overrides"}
    return run(Settings(**values, overrides=tuple(args.overrides)))


def _unpack(args) -> int:
    for folder in unpack(Path(args.files), Path(args.dest)):
        print(folder)
    return 0


def main(argv: list[str] | None = None) -> int:
    """One command; a PipelineError prints one line (``error: ...``) and exits 2, as ``python -m pipeline`` does."""
    parser = build_parser()
    # key=value overrides may follow options too (`run --batch 2 seed=3`), as in python -m pipeline
    args, extra = parser.parse_known_args(argv)
    stray = [a for a in extra if a.startswith("-") or "=" not in a or args.command != "run"]
    if stray:
        parser.error(f"unrecognized arguments: {' '.join(stray)}")
    if extra:
        args.overrides = [*args.overrides, *extra]
    try:
        return args.fn(args)
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
