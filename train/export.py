"""Export a trained run as a self-contained model folder (``python -m pipeline export``; the shipped model),
and change an exported one after training (its strength, σ's scale, its base).

    python -m pipeline export --config configs/ship.yaml --spp any --out train/shipped

The folder holds everything ``train.model.load`` needs, named relative to itself, so it works from
any checkout and any working directory:

    model.json            the run's record (the base's SHA-256, the formulation, the metrics, the settings)
    control.safetensors   the Control Module (float16)
    base.tza              the frozen base (OIDN's float16 weights)
    oidn_ft/              OIDN fine-tuned for inputs without albedo or normal (kept when already in --out)
    README.md             the model card: data, formulation, training, validation numbers, the commands

The dates it records are today's, or that of ``SOURCE_DATE_EPOCH`` when set (a reproducible export).

Weights are stored in float16 (half the size in the repository and in a GPU run's 64 MiB; loading
turns them back into float32): the shipped model is evaluated from the exported files, so the
numbers its card and ``docs/example_report`` give are those of what ships.
"""
from __future__ import annotations

import datetime
import json
import os
import shlex
import shutil
from pathlib import Path

import numpy as np

from mcdenoise.pipeline import weights
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.errors import CheckpointError, ConfigError
from mcdenoise.pipeline.exr import StoreError, atomic_write_json

from .model import run_dir


def train_command(args: str, config: str | None) -> str:
    """The make line that trains what an export needs, on the config the export was given (its runs)."""
    return f"make train {args}" + (f" CONFIG={config}" if config else "")


def export(cfg: Config, spp, out: Path, quiet: bool = False, config: str | None = None,
           overrides: list[str] | tuple = ()) -> Path:
    """The run ``diffusion_spp<spp>[_<name>]`` as a model folder: model.json, control.safetensors (float16),
    base.tza (the frozen OIDN weights), README.md; an ``oidn_ft/`` folder already in ``out`` (OIDN fine-tuned
    for inputs without albedo or normal) is kept."""
    folder = run_dir(cfg, spp)
    meta = weights.read_record(folder, "oidn_control", f"run `{train_command(f'SPP={spp}', config)}` first")
    tmp = out.parent / (out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:                 # the model folder is built in out.tmp; a failed build (full disk, ...) removes it
        kept = out if out.is_dir() else _aside(out)      # a kill in _publish may have left it aside
        if (kept / "oidn_ft").is_dir():
            shutil.copytree(kept / "oidn_ft", tmp / "oidn_ft")
        shutil.copy(folder / "base.tza", tmp / "base.tza")
        state = weights.load_tensors(folder / "control.safetensors")
        record = {**meta, "exported": {"from": str(folder.resolve()), "date": _today()}}
        weights.save(tmp, "oidn_control", {k: _half(v) for k, v in state.items()}, record, weights="control.safetensors")
        (tmp / "README.md").write_text(model_card(cfg, record, folder, config or "<config>", out, overrides))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return _publish(tmp, out, folder, quiet)


def _today() -> str:
    """The date a model folder records (ISO): today, or the date of ``SOURCE_DATE_EPOCH`` when set (the
    reproducible-builds convention), so that two exports of one run can be byte for byte the same."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if epoch is None:
        return datetime.date.today().isoformat()
    try:
        return datetime.datetime.fromtimestamp(int(epoch), datetime.timezone.utc).date().isoformat()
    except (ValueError, OverflowError, OSError):
        raise ConfigError(f"SOURCE_DATE_EPOCH={epoch!r}: expected whole seconds since 1970-01-01 UTC") from None


def _aside(out: Path) -> Path:
    return out.parent / (out.name + ".old")


def _publish(tmp: Path, out: Path, folder: Path, quiet: bool) -> Path:
    """Replace ``out`` by the finished ``tmp`` folder (a rename: no half-written model folder) and say so.
    The old ``out`` is moved aside before and removed after, so a kill in between leaves what a rerun keeps
    from it (``oidn_ft/``)."""
    aside = _aside(out)
    if out.exists():
        shutil.rmtree(aside, ignore_errors=True)
        out.rename(aside)
    tmp.rename(out)
    shutil.rmtree(aside, ignore_errors=True)
    if not quiet:
        size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
        print(f"exported {folder} -> {out} ({size / 2**20:.1f} MiB)", flush=True)
    return out


def _half(v):
    return v.half().contiguous() if v.is_floating_point() else v


def _split_sizes(store: str) -> str:
    """The frames of each split in the store (what the model saw: fewer than the config plans if a render stopped)."""
    manifest = Path(store) / "dataset.json"
    if not manifest.exists():
        return ""
    splits = json.loads(manifest.read_text()).get("splits", {})
    return " Frames in the store: " + ", ".join(f"{len(v)} {k}" for k, v in splits.items() if v) + "."


def _gt_spp(d) -> str:
    """The ground truths' sample count as the card states it: fixed, or rendered to a target error."""
    if d.gt_target_psnr is None:
        return f"{d.gt_spp} spp"
    return f"to an estimated {d.gt_target_psnr:g} dB in passes of {d.gt_pass_spp} spp (at most {d.gt_max_spp} spp)"


def export_oidn(cfg: Config, out: Path | None = None, quiet: bool = False, config: str | None = None,
                overrides: list[str] | tuple = ()) -> Path:
    """The oidn_ft run of ``oidn_ft.network`` (blended by ``oidn_ft.blend``) as a float16 TZA file that
    OIDN 2.x loads as custom weights (``train.oidn``; a host's filter parameter ``weights``), with a
    ``.json`` sidecar (network, blend, validation scores, sha256). ``out``: a ``.tza`` path, or a folder
    that gets ``<network>.tza``; default ``<runs>/oidn_ft_<network>.tza``."""
    from mcdenoise.pipeline.config import run_dir as runs_dir
    from mcdenoise.pipeline.exr import atomic_write_bytes

    from .baselines.oidn_ft import export_blob, load_run

    folder = runs_dir(cfg, "oidn_ft")
    if not (folder / "model.safetensors").exists():
        raise StoreError(f"{folder}: no oidn_ft run to export "
                         f"(run `{train_command('MODEL=oidn_ft SPP=any', config)}` first)")
    net, record = load_run(folder, cfg)
    name = record["network"]
    if out is None:
        out = folder.parent / f"{folder.name}.tza"
    elif out.is_dir() or not out.suffix:
        out = out / f"{name}.tza"
    out.parent.mkdir(parents=True, exist_ok=True)
    blob = export_blob(net)
    atomic_write_bytes(out, lambda tmp: Path(tmp).write_bytes(blob))
    import hashlib
    command = f"python -m pipeline export --format oidn --config {config or '<config>'} --out {out}" + "".join(
        f" {shlex.quote(o)}" for o in overrides)
    atomic_write_json(out.with_suffix(".json"), {
        "network": name, "blend": record["blend"], "sha256": hashlib.sha256(blob).hexdigest(), "bytes": len(blob),
        "prior_sha256": record["prior_sha256"], "epoch": record["epoch"], "metrics": record["metrics"],
        "spp": record["spp"], "store": record["store"], "settings": record["settings"],
        "exported": {"from": str(folder.resolve()), "date": _today(), "command": command}})
    if not quiet:
        print(f"exported {folder} (blend {record['blend']:g}) -> {out} ({len(blob) / 2**20:.2f} MiB, float16 TZA; "
              f"OIDN runs it as its '{name}' network: denoise --oidn-weights {out})", flush=True)
    return out


def rebase(model: Path, blend: float, out: Path | None = None, oidn_weights_file: str = "", quiet: bool = False) -> Path:
    """An exported model on OIDN's network whose base is OIDN + ``base_blend`` × what an oidn_ft run
    changed (model.json), with that base moved to OIDN + ``blend`` × the same change (``oidn_ft.blend``'s
    WiSE-FT knob, after training) and everything else kept: a new model to validate, since its Control
    Module was trained on the old base. ``out`` (default: ``model`` itself) is replaced by a rename."""
    from mcdenoise.pipeline.weights import TZATensor, read_tza, write_tza
    from mcdenoise.train import oidn

    from .baselines.oidn_ft import blended

    model = Path(model)
    out = Path(out) if out else model
    meta = weights.read_record(model, "oidn_control", "give a model folder exported from a run on OIDN's network")
    old = meta.get("base_blend")
    if old is None:
        raise CheckpointError(f"{model / 'model.json'}: no base_blend (how far its base is from OIDN): only a base "
                              f"made from an oidn_ft run at a known blend can be moved; base: {meta.get('base_what')}")
    if not old:
        raise CheckpointError(f"{model / 'model.json'}: base_blend 0, its base is OIDN itself: no fine-tuning to move "
                              "along (train on a fine-tuned base: diffusion.base=oidn_ft)")
    name = meta["base_network"]
    stock = read_tza(oidn.weights_blob(name, oidn.weights_source(name, oidn_weights_file)), name)
    base = read_tza((model / meta["base"]).read_bytes(), str(model / meta["base"]))
    moved = blended({k: t.array.astype(np.float32) for k, t in stock.items()},
                    {k: t.array.astype(np.float32) for k, t in base.items()}, float(blend) / float(old))
    blob = write_tza({k: TZATensor(moved[k].astype(np.float16), t.layout) for k, t in base.items()})
    what = f"{meta.get('base_what')}, moved from blend {old:g} to {blend:g} after training"
    return _updated(model, meta, out, quiet, _rebase_note(model, out, old, blend), blob,
                    base_blend=float(blend), base_what=what,
                    rebased={"from": old, "to": float(blend), "date": _today()})


def swap_base(model: Path, base_file: Path, out: Path | None = None, quiet: bool = False) -> Path:
    """An exported model on OIDN's network with its frozen base replaced by ``base_file`` (a float16 TZA of the
    same network, e.g. an ``export --format oidn`` file; its blend from the card beside it, ``<file>.json``) and
    its Control Module kept: the start of a warm-started run on another base (``diffusion.init``), or a model
    to validate as it is. ``out`` (default: ``model`` itself) is replaced by a rename."""
    from mcdenoise.pipeline.weights import read_tza

    model, base_file = Path(model), Path(base_file)
    out = Path(out) if out else model
    meta = weights.read_record(model, "oidn_control", "give a model folder exported from a run on OIDN's network")
    if not base_file.is_file():
        raise CheckpointError(f"{base_file}: no such weights file (give a .tza of OIDN's {meta['base_network']})")
    blob = base_file.read_bytes()
    new, old = read_tza(blob, str(base_file)), read_tza((model / meta["base"]).read_bytes(), str(model / meta["base"]))
    shapes = lambda ts: {k: tuple(t.array.shape) for k, t in ts.items()}  # noqa: E731
    if shapes(new) != shapes(old):
        raise CheckpointError(f"{base_file}: not OIDN's {meta['base_network']} (its tensors differ from "
                              f"{model / meta['base']}'s): the Control Module feeds that network's decoder")
    card = base_file.with_suffix(".json")
    blend = json.loads(card.read_text()).get("blend") if card.exists() else None
    return _updated(model, meta, out, quiet, _swap_note(model, base_file, out, blend), blob,
                    base_blend=blend, base_what=f"{base_file} (blend {blend})",
                    base_swapped={"from": meta.get("base_what"), "to": str(base_file),
                                  "date": _today()})


def _updated(model: Path, meta: dict, out: Path, quiet: bool, note: str, blob: bytes | None = None, **record) -> Path:
    """``model`` copied to ``out`` (by a rename) with model.json updated by ``record``, ``note`` appended to its
    card and, given ``blob``, that as its frozen base (and the base's sha256 in model.json)."""
    import hashlib

    tmp = out.parent / (out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(model, tmp)
    if blob is not None:
        (tmp / meta["base"]).write_bytes(blob)
        record["base_sha256"] = hashlib.sha256(blob).hexdigest()
    atomic_write_json(tmp / weights.RECORD, {**meta, **record})
    card = tmp / "README.md"
    if card.exists():
        card.write_text(card.read_text().rstrip("\n") + "\n\n" + note)
    return _publish(tmp, out, model, quiet)


def set_strength(model: Path, strength: float, out: Path | None = None, quiet: bool = False) -> Path:
    """An exported model on OIDN's network that applies ``strength`` of its Control Module's change
    (model.json ``strength``; ``train.sampler.with_strength``), written to ``out`` (default: ``model`` itself)
    by a rename; its weights unchanged."""
    from .sampler import check_strength

    model = Path(model)
    out = Path(out) if out else model
    meta = weights.read_record(model, "oidn_control", "give a model folder exported from a run on OIDN's network")
    k = check_strength(strength, "--strength")
    note = (f"## Strength set after training ({_today()})\n\nThe model applies {k:g} of "
            f"what its Control Module changes to its base's output (it was {meta.get('strength', 1.0):g}); the "
            f"weights are unchanged. Made by:\n\n```sh\npython -m pipeline export --from {model} --strength {k:g} "
            f"--out {out}\n```\n")
    fitted_at = (meta.get("sigma") or {}).get("strength", 1.0)
    if meta.get("sigma") and fitted_at != k:
        # strength scales the samples' spread and the mean's change, not the error: σ's scale is stale
        refit = f"python -m pipeline export --from {out} --fit-sigma --config <the config of its validation store>"
        note += f"\nσ's scale was fitted at strength {fitted_at:g}; refit it at this strength with `{refit}`.\n"
        if not quiet:
            print(f"{out}: σ's scale was fitted at strength {fitted_at:g}; refit it: {refit}", flush=True)
    return _updated(model, meta, out, quiet, note, strength=k)


def fit_sigma(cfg: Config, model: Path, out: Path | None = None, quiet: bool = False, config: str | None = None,
              overrides: list[str] | tuple = ()) -> Path:
    """An exported model on OIDN's network with σ's scale (model.json ``sigma``, ``train.infer.calibrate``)
    fitted again on the first ``diffusion.val_frames`` val frames of ``cfg``'s store at the model's own
    strength, written to ``out`` (default: ``model`` itself) by a rename; its weights unchanged."""
    from .data import StoreSource
    from .infer import calibrate, load_denoiser

    model = Path(model)
    out = Path(out) if out else model
    meta = weights.read_record(model, "oidn_control", "give a model folder exported from a run on OIDN's network")
    source = StoreSource(cfg, meta["base_network"])
    keys = source.val_keys[:cfg.diffusion.val_frames]
    if not keys:
        raise StoreError(f"{cfg.store}: no val frames to fit σ on (diffusion.val_frames={cfg.diffusion.val_frames}); "
                         "render the dataset or give the config of a store that has a val split")
    fit = calibrate(load_denoiser(model, cfg.diffusion.device), source.val_items(meta["spp"], len(keys)), cfg.seed)
    fit.update(store=str(cfg.store), frames=len(keys))
    command = shlex.join(["python", "-m", "pipeline", "export", "--from", str(model), "--fit-sigma", "--out", str(out),
                          *(["--config", config] if config else []), *overrides])
    note = (f"## σ fitted again ({_today()})\n\nσ's scale is now {fit['scale']:.3g} (was "
            f"{(meta.get('sigma') or {}).get('scale', 1.0):.3g}), fitted at strength {fit['strength']:g} on "
            f"{fit['pixels']} pixels of {len(keys)} val frames of `{cfg.store}` ({fit['steps']} steps, "
            f"{fit['samples']} samples); the weights are unchanged. Made by:\n\n```sh\n{command}\n```\n")
    if not quiet:
        print(f"{model}: σ scale {fit['scale']:.3g} fitted at strength {fit['strength']:g} on {fit['pixels']} "
              f"pixels of {len(keys)} val frames of {cfg.store}", flush=True)
    return _updated(model, meta, out, quiet, note, sigma=fit)


def _swap_note(model: Path, base_file: Path, out: Path, blend) -> str:
    return (f"## Base replaced after training ({_today()})\n\nThe base is now `{base_file}` "
            f"(blend {blend}); the Control Module above was trained on the previous base and is unchanged. Made by:"
            f"\n\n```sh\npython -m pipeline export --from {model} --base {base_file} --out {out}\n```\n")


def _rebase_note(model: Path, out: Path, old: float, new: float) -> str:
    return (f"## Base moved after training ({_today()})\n\nThe base is now OIDN + {new:g} "
            f"x what fine-tuning changed (it was {old:g} before this move; the training record above is the model "
            "it was trained as); the Control Module is unchanged. Made by:\n\n```sh\n"
            f"python -m pipeline export --from {model} --base-blend {new:g} --out {out}\n```\n")


# Config sections that decide what the dataset and gt-clean stages write (the rest is training).
_DATA_KEYS = ("seed=", "store=", "dataset.", "scene.", "render.", "clean.")


def data_commands(config: str, overrides) -> list[str]:
    """The card's dataset and gt-clean lines, with the overrides that change their data (a run trained on
    ``scene.texture_probability=0.3`` says so where its data is made, not only where it is trained)."""
    data = "".join(f" {shlex.quote(o)}" for o in overrides if str(o).startswith(_DATA_KEYS))
    return [f"python -m pipeline {c} --config {config}{data}" for c in ("dataset", "gt-clean")]


def model_card(cfg: Config, record: dict, run: Path, config: str, out: Path, overrides) -> str:
    """The model card of an exported OIDN-based denoiser: what it is, its data, training, validation, commands."""
    train = json.loads((run / "train.json").read_text()) if (run / "train.json").exists() else {}
    lines = [*_card_what_it_is(record, run), *_card_data(cfg, config), *_card_training(cfg, record, train),
             *_card_commands(cfg, record, config, out, overrides)]
    return "\n".join(lines)


def _card_what_it_is(record: dict, run: Path) -> list[str]:
    """The card's title, where the model came from and its "What it is" section."""
    f = record.get("formulation", {})
    sig = record.get("sigma") or {}
    return [
        "# The shipped denoiser: a Control Module on OIDN's network", "",
        f"Exported from `{run}` on {record['exported']['date']}; loaded by `python -m pipeline denoise --exr IN.exr "
        "--out OUT.exr` and `make eval`'s `ours` rows wherever a config has no trained run of its own "
        "(`diffusion.shipped`).", "",
        "## What it is", "",
        f"- Base: OIDN's `{record.get('base_network')}` network ({record.get('base_what')}), frozen, in `base.tza` "
        "(OIDN's own float16 format; sha256 in model.json).",
        "- Control Module (`control.safetensors`, float16): a copy of OIDN's encoder reading OIDN's input, every other "
        f"buffer ({len(record.get('cond_channels', []))} condition channels, model.json `cond_channels`), z_t and t, "
        "into OIDN's decoder through zero-initialised 1x1 convolutions (train/model.py).",
        f"- Refine formulation around OIDN's output in OIDN's space: x0-prediction, `{f.get('schedule')}` schedule, "
        f"residual scale {f.get('residual_scale')}, default sampler {f.get('sampler')} with {f.get('steps')} step(s) "
        f"from `{f.get('start')}` (train/sampler.py).",
        f"- Sample counts: {record.get('spp')} (the spp map is an input). Inputs without variances, the radiance split "
        "or the material buffers are served (trained with buffer-group dropout); without albedo and normal OIDN runs "
        "instead (`oidn_ft/` networks when present).",
        f"- σ (`--samples K`, the `std` layer): scaled by {sig.get('scale', 1.0):.3g}, fitted on "
        f"{sig.get('pixels', '?')} validation pixels at {sig.get('steps', '?')} steps and {sig.get('samples', '?')} "
        "samples (median |error| / σ = 0.6745).", ""]


def _card_data(cfg: Config, config: str) -> list[str]:
    """The card's "Data" section: the config, the store and what the dataset stage rendered."""
    d = cfg.dataset
    return [
        "## Data", "",
        f"`{config}`, store `{cfg.store}` (seed {cfg.seed}): {d.scenes} random scenes and the stress presets x "
        f"{d.stress_copies} ({d.stress_split} split), {d.frames} frame(s) each, {d.resolution[0]}x{d.resolution[1]}, "
        f"GT {_gt_spp(d)} x 2 cleaned by the GT cleaner, {d.stacks} stacks of {d.stack_spp} spp. None of "
        f"configs/default.yaml's scenes (another seed).{_split_sizes(cfg.store)}", ""]


def _card_training(cfg: Config, record: dict, train: dict) -> list[str]:
    """The card's "Training" section: the settings, the best epoch, the machine and the table of epochs."""
    hist, best, m = train.get("history", []), train.get("best") or {}, train.get("machine") or {}
    f, st = record.get("formulation", {}), record.get("settings", {})
    # The per-spp gain columns are those the last epoch's validation reports.
    gain_keys = sorted((k for k in (hist[-1].get("val") or {} if hist else {}) if k.startswith("gain_spp")),
                       key=lambda k: int(k[8:]))
    v = best.get("val") or {}
    init = cfg.diffusion.init
    lines = [
        "## Training", "",
        f"{len([h for h in hist if h['epoch'] > 0])} epochs, {hist[-1]['seconds'] if hist else '?'} s; lr "
        f"{st.get('lr')}, batch {st.get('batch_size')}, crop {st.get('crop')}, EMA {st.get('ema')}, buffer-group "
        f"dropout {st.get('dropout')}, loss: tonemapped MSE over OIDN's + {st.get('hdr_weight')} x PU L1 over OIDN's, "
        f"per crop; t_focus {f.get('t_focus')} on {st.get('train_steps')}-step samplers. Best epoch "
        f"{best.get('epoch')} by validation PSNR: {v.get('psnr', float('nan')):.3f} dB against its base's "
        f"{v.get('estimate_psnr', float('nan')):.3f} dB " + (f"(epoch 0 is the model it started from, `{init}`)."
                                                             if init else "(epoch 0 is the base itself)."), "",
        f"Machine: {m.get('cuda') or m.get('processor', '?')}, {m.get('platform', '?')}, {m.get('cpus', '?')} CPUs, "
        f"{m.get('torch_threads', '?')} torch threads, {m.get('ranks', '?')} rank(s), torch {m.get('torch', '?')}, "
        f"device {m.get('device', '?')}.", "",
        "| epoch | val PSNR dB | base dB | gain dB | " + " | ".join(f"gain {k[8:]} spp" for k in gain_keys)
        + " | seconds |", "| --- | --- | --- | --- |" + " --- |" * len(gain_keys) + " --- |"]
    for h in hist:
        hv = h.get("val") or {}
        gains = [f"{hv[k]:+.3f}" if k in hv else "" for k in gain_keys]
        lines.append(f"| {h['epoch']} | {hv.get('psnr', float('nan')):.3f} | {hv.get('estimate_psnr', float('nan')):.3f} "
                     f"| {hv.get('psnr', 0) - hv.get('estimate_psnr', 0):+.4f} | " + " | ".join(gains)
                     + f" | {h.get('seconds')} |")
    return lines


def _card_commands(cfg: Config, record: dict, config: str, out: Path, overrides) -> list[str]:
    """The card's "How it was made" section: the commands that remake the model, and where its evaluation is."""
    extra = "".join(f" {shlex.quote(o)}" for o in overrides)
    spp = record.get("spp")
    spp = "any" if isinstance(spp, list) and len(spp) > 1 else spp
    return ["", "## How it was made (each command resumes where it stopped)", "", "```sh",
            *data_commands(config, overrides),
            *([f"python -m pipeline train --model oidn_ft --spp any --config {config}{extra}"]
              if cfg.diffusion.base == "oidn_ft" and not cfg.diffusion.init else []),   # the base: OIDN fine-tuned, blended
            f"python -m pipeline train --model diffusion --spp {spp} --config {config}{extra}",
            f"python -m pipeline export --config {config} --spp {spp} --out {out}{extra}", "```", "",
            "Evaluation against OIDN, oidn_ft, Isik and the noisy input on the default test set: "
            "docs/example_report/eval.md; the ablation: docs/diffusion.md.", ""]
