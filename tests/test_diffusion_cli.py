"""The diffusion stage through the real command line on configs/tiny.yaml: pretrain, train (also under
torchrun with 2 CPU processes), denoise a store frame and a foreign EXR, and the errors users meet."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from mcdenoise.pipeline.exr import read_image

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.yaml"
SMALL = ["pretrain.channels=[16,32]", "pretrain.crop=16", "pretrain.epochs=1", "diffusion.crop=16",
         "diffusion.batch_size=2", "diffusion.val_skip=24", "diffusion.val_frames=1"]
# Most tests: the paper's arrangement (a pretrained base, frozen) with OIDN as the first estimate;
# test_default_formulation_end_to_end runs the defaults (OIDN + Isik, a new base that trains).
FROZEN = ["diffusion.estimate=oidn", "diffusion.train_base=false"]


def run(*args, check=True, module=("-m", "pipeline")):
    proc = subprocess.run([sys.executable, *module, *map(str, args)], cwd=ROOT, capture_output=True, text=True,
                          timeout=900)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr[-4000:]}")
    return proc


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("diffusion")
    keys = ["--config", TINY, f"store={tmp / 'store'}", f"runs={tmp / 'runs'}", *SMALL, *FROZEN]
    run("dataset", *keys, "--quiet")
    run("gt-clean", *keys, "clean.epochs=1", "--quiet")
    proc = run("pretrain", *keys)
    assert "base written to" in proc.stdout
    keys.append(f"diffusion.base={tmp / 'runs' / 'base'}")
    return tmp, keys


def test_pretrain_writes_a_loadable_base(setup):
    tmp, _ = setup
    base = tmp / "runs" / "base"
    assert {p.name for p in base.iterdir()} >= {"config.json", "diffusion_pytorch_model.safetensors",
                                                 "prompt_embeds.safetensors", "training.json"}
    assert json.loads((base / "config.json").read_text())["in_channels"] == 6


def test_train_then_denoise(setup, tmp_path):
    tmp, keys = setup
    proc = run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=2")
    assert "diffusion_spp4: 2 epochs (2 this run" in proc.stdout and "val PSNR" in proc.stdout
    folder = tmp / "runs" / "diffusion_spp4"
    meta = json.loads((folder / "model.json").read_text())
    assert meta["spp"] == "4" and len(meta["aux_channels"]) > 30
    assert (folder / "loss.png").exists() and (folder / "last.safetensors").exists()
    # A second run with the same epochs does nothing.
    assert "already trained" in run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=2").stdout

    scene = sorted(p.name for p in (tmp / "store" / "scenes").iterdir())[0]
    out = tmp_path / "den.exr"
    proc = run("denoise", "--spp", "4", "--frame", f"{scene}/000", "--out", out, "--steps", "3", "--samples", "3",
               *keys)
    img, rec = read_image(out)
    assert img["color"].shape == (24, 32, 3) and np.isfinite(img["color"]).all()
    assert rec["method"] == "ours" and rec["steps"] == 3 and rec["samples"] == 3 and rec["layers"] == ["std"]
    std = _layer(out, "std")
    assert std.shape == (24, 32, 3) and (std >= 0).all() and std.max() > 0   # three samples differ somewhere
    run("denoise", "--spp", "4", "--frame", f"{scene}/000", "--out", out, "--steps", "3", *keys)
    assert not _layer(out, "std").any()                                     # one sample: no spread

    # A foreign EXR: only R, G, B (+ a NaN that must be repaired and counted).
    rgb = np.random.default_rng(0).random((20, 28), np.float32)
    rgb[3, 4] = np.nan
    foreign = tmp_path / "foreign.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {c: rgb.copy() for c in "RGB"}) as f:
        f.write(str(foreign))
    proc = run("denoise", "--spp", "4", "--exr", foreign, "--out", tmp_path / "f.exr", *keys)
    assert "3 non-finite input values replaced by 0" in proc.stdout   # one NaN pixel in R, G and B
    img, rec = read_image(tmp_path / "f.exr")
    assert img["color"].shape == (20, 28, 3) and np.isfinite(img["color"]).all() and rec["repaired_nonfinite"] == 3


def _layer(path, name):
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        return np.stack([ch[f"{name}.{c}"].pixels for c in "RGB"], axis=2)


def test_torchrun_two_cpu_processes(setup):
    tmp, keys = setup
    keys = [k for k in keys if not str(k).startswith("runs=")] + [f"runs={tmp / 'ddp'}"]
    proc = run("--nproc_per_node", "2", "-m", "pipeline", "train", "--model", "diffusion", "--spp", "4", *keys,
               "diffusion.epochs=1", module=("-m", "torch.distributed.run"))
    assert "DDP: 2 ranks in sync" in proc.stdout, proc.stdout + proc.stderr[-2000:]
    assert (tmp / "ddp" / "diffusion_spp4" / "control.safetensors").exists()


def test_errors_are_one_line_and_exit_2(setup, tmp_path):
    tmp, keys = setup
    proc = run("train", "--model", "diffusion", "--spp", "4", "--config", TINY, f"store={tmp_path / 'none'}",
               check=False)
    assert proc.returncode == 2 and "no dataset" in proc.stderr
    proc = run("denoise", "--spp", "16", "--frame", "s00000/000", "--out", tmp_path / "x.exr", *keys,
               "diffusion.shipped=false", check=False)           # no run at 16 spp and no shipped fallback
    assert proc.returncode == 2 and "no diffusion checkpoint" in proc.stderr
    assert not (tmp_path / "x.exr").exists()
    proc = run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.base=/nonexistent", check=False)
    assert proc.returncode == 2 and "config.json: missing" in proc.stderr
    proc = run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.skip=27", check=False)
    assert proc.returncode == 2 and "diffusion.skip" in proc.stderr
    proc = run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.prediction=epsilon", check=False)
    assert proc.returncode == 2 and "zero terminal SNR" in proc.stderr and "Traceback" not in proc.stderr
    proc = run("denoise", "--spp", "4", "--frame", "s00000/000", "--out", tmp_path / "x.exr", "--steps", "2",
               "--skip", "2", *keys, check=False)
    assert proc.returncode == 2 and "diffusion.skip" in proc.stderr and not (tmp_path / "x.exr").exists()


def test_a_run_resumes_only_with_its_epoch_steps(setup, tmp_path):
    tmp, keys = setup
    keys = [k for k in keys if not str(k).startswith("runs=")] + [f"runs={tmp_path / 'runs'}"]
    run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=1", "diffusion.epoch_steps=1")
    proc = run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=1", "diffusion.epoch_steps=2",
               check=False)
    assert proc.returncode == 2 and "epoch_steps" in proc.stderr


def test_eval_runs_the_trained_model(setup, tmp_path):
    """The evaluator loads the real trained run (not a stand-in) and reports it next to the noisy input."""
    tmp, keys = setup
    run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=2")
    run("eval", *keys, "eval.methods=[noisy,ours,ours_s3_k2,base_only_s1]",
        "eval.metrics=[l1,psnr]",
        "eval.equal_time=none", "eval.split=train", "eval.frames=1", f"eval.out={tmp_path / 'rep'}",
        "--spp", "4")
    md = (tmp_path / "rep" / "eval.md").read_text()
    assert "not available" not in md, md
    for name in ("ours", "ours_s3_k2", "base_only_s1"):
        row = next(line for line in md.splitlines() if line.startswith("|") and f"(`{name}`)" in line)
        l1, psnr_db = (float(c.strip(" *")) for c in row.split("|")[2:4])
        assert 0 <= l1 < 6 and 0 < psnr_db < 100, row
    assert (tmp_path / "rep" / "crops_train_spp4.png").stat().st_size > 1000
    rows = json.loads((tmp_path / "rep" / "eval.json").read_text())["groups"]["train"]["spp"]["4"]["methods"]
    u = rows["ours_s3_k2"]["uncertainty"]            # the mean of 2 samples carries their spread
    assert u["frames"] == 1 and u["calibration"] and all(b["std"] >= 0 and b["rmse"] >= 0 for b in u["calibration"])
    assert "uncertainty" not in rows["ours"] and (tmp_path / "rep" / "uncertainty_train_spp4.png").exists()
    assert "Spearman" in md


def test_bench_denoise_reports_every_step_count(setup, tmp_path):
    tmp, keys = setup
    run("bench-denoise", *keys, "diffusion.tile=32", "diffusion.tile_overlap=8", "--side", 32, "--out", tmp_path)
    result = json.loads((tmp_path / "denoise.json").read_text())
    rows = result["rows"]
    assert not result["estimate_only"]          # the timed frames reach the network, not just the estimate
    assert [r["steps"] for r in rows] == [1, 3, 9, 27]
    assert all(r["side"] == 32 and r["seconds_frame"] > 0 and r["seconds_per_megapixel"] > 0 for r in rows)


def test_pack_equals_the_store_reader(setup):
    """Every pack item equals what the store reader and the model's encoders give for the same stacks,
    within float16 rounding; a pack made for another estimate is refused."""
    from mcdenoise.pipeline.store import Store
    from mcdenoise.train.data import frame_rotation, model_inputs, to_planar
    from mcdenoise.train.estimate import Estimator
    from mcdenoise.train.pack import PackPairs, build_pack, variant_stacks

    tmp, _ = setup
    store = Store(tmp / "store")
    keys = [k for k in store.frames("train") if store.image_path(k.scene, k.frame, "gt_clean").exists()]
    path = tmp / "pack_test.safetensors"
    header = build_pack(store, keys, path, estimator=Estimator("oidn"), quiet=True)
    assert header["variants"] == {"4": 2, "16": 1}          # the tiny store has 4 stacks of 4 spp
    ds = PackPairs(path, crop=None, estimate="oidn")
    assert len(ds) == 3 * len(keys)
    seen = {}
    for i in range(len(ds)):
        item, t = ds[i], ds.t
        key, spp = keys[int(t["frame"][ds.index[i]])], int(t["spp"][ds.index[i]])
        variant = seen.setdefault((key, spp), -1) + 1
        seen[(key, spp)] = variant
        buffers = store.read(key.scene, key.frame, spp, stacks=variant_stacks(spp, 4, variant, 4))
        noisy, aux = model_inputs(buffers, spp, frame_rotation(store, key))
        gt = store.read_image(key.scene, key.frame, "gt_clean", ["color"])[0]["color"]
        for name, ref in (("noisy", noisy), ("aux", aux), ("image", to_planar(Estimator("oidn")(buffers)[0])),
                          ("target", to_planar(gt))):
            np.testing.assert_allclose(item[name].numpy(), ref, atol=1e-3, rtol=1e-3, err_msg=name)
    with pytest.raises(Exception, match="another estimate"):
        PackPairs(path, crop=None, estimate="none")
    crop = PackPairs(path, crop=8, crops_per_item=2, seed=1, estimate="oidn", spp_choices=[4])
    assert len(crop) == 2 * 2 * len(keys) and crop[0]["aux"].shape[-2:] == (8, 8)


def test_export_is_self_contained_and_serves_as_the_shipped_model(setup, tmp_path, monkeypatch):
    """An exported run loads from anywhere (relative base), denoises as the run does (within its float16
    weights), and is what a config without runs of its own falls back to; diffusion.shipped=false turns
    the fallback off."""
    import mcdenoise.train.model as tm
    from mcdenoise.pipeline.config import load_config
    from mcdenoise.pipeline.store import Store
    from mcdenoise.train.infer import load_denoiser

    tmp, keys = setup
    run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=2", "diffusion.loss_norm=crop")
    out = tmp_path / "moved" / "shipped"
    run("export", "--spp", "4", "--out", out, *keys, "diffusion.loss_norm=crop")
    meta = json.loads((out / "model.json").read_text())
    assert meta["base"] == "base" and (out / "base" / "config.json").exists() and (out / "README.md").exists()
    assert meta["formulation"]["loss_norm"] == "crop"
    card = (out / "README.md").read_text()          # the card's commands make this model again
    train_line = next(line for line in card.splitlines() if line.startswith("python -m pipeline train --model diffusion"))
    assert "diffusion.loss_norm=crop" in train_line and all(k in train_line for k in cfg_overrides(keys))
    data_line = next(line for line in card.splitlines() if line.startswith("python -m pipeline dataset"))
    assert f"store={tmp / 'store'}" in data_line and "diffusion." not in data_line   # the data's keys, only them
    store = Store(tmp / "store")
    key = store.frames("test")[0]
    buffers = store.read(key.scene, key.frame, 4)
    a = load_denoiser(tmp / "runs" / "diffusion_spp4", device="cpu").denoise(buffers, spp=4, seed=3)
    b = load_denoiser(out, device="cpu").denoise(buffers, spp=4, seed=3)
    np.testing.assert_allclose(a, b, rtol=2e-2, atol=2e-3)
    assert (out / "control.safetensors").stat().st_size < 0.6 * (tmp / "runs" / "diffusion_spp4" /
                                                                "control.safetensors").stat().st_size
    monkeypatch.setattr(tm, "SHIPPED_MODEL", out)
    overrides = [k for k in cfg_overrides(keys) if not k.startswith("runs=")] + [f"runs={tmp_path / 'none'}"]
    cfg = load_config(TINY, overrides)
    assert tm.find_run(cfg, 16) == out
    with pytest.raises(Exception, match="no diffusion checkpoint"):
        tm.find_run(load_config(TINY, [*overrides, "diffusion.shipped=false"]), 16)


def cfg_overrides(keys):
    return [str(k) for k in keys if "=" in str(k)]


def test_default_formulation_end_to_end(setup, tmp_path):
    """The defaults: the Isik network (SPP=any) and OIDN as the first estimate, a new base with a zero last
    layer trained with the Control Module; epoch 0 is the estimate itself and is scored first."""
    tmp, keys = setup
    default = [k for k in keys if not str(k).startswith(("diffusion.base=", "diffusion.estimate=",
                                                           "diffusion.train_base=", "runs="))]
    default.append(f"runs={tmp_path / 'runs'}")
    missing = run("train", "--model", "diffusion", "--spp", "any", *default, "diffusion.epochs=1", check=False)
    assert missing.returncode == 2 and "make train MODEL=isik SPP=any" in missing.stderr
    run("train", "--model", "isik", "--spp", "any", *default, "clean.epochs=1", "--quiet")
    run("train", "--model", "diffusion", "--spp", "any", *default, "diffusion.epochs=1", "diffusion.val_frames=2")
    folder = tmp_path / "runs" / "diffusion_sppany"
    meta = json.loads((folder / "model.json").read_text())
    hist = json.loads((folder / "train.json").read_text())["history"]
    assert meta["formulation"]["estimate"] == "oidn+isik" and meta["train_base"] and meta["isik_sha256"]
    assert len(meta["aux_channels"]) == len(json.loads((tmp / "runs" / "diffusion_spp4" / "model.json")
                                                       .read_text())["aux_channels"]) + 6
    assert hist[0]["epoch"] == 0 and hist[0]["val"]["psnr"] == pytest.approx(hist[0]["val"]["estimate_psnr"], abs=1e-6)
    assert (folder / "base_init" / "config.json").exists()


def test_gpu_recipe_continues_only_a_model_on_oidn_and_its_flags_are_its_settings(tmp_path):
    """Another model folder gets one line naming it (exit 2), not a traceback; every flag is a setting."""
    import dataclasses

    from mcdenoise.pipeline.__main__ import build_parser
    from mcdenoise.train.gpu_recipe import Settings

    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "model.json").write_text(json.dumps({"format": "mcdenoise-control"}))
    proc = run("gpu-recipe", "--model", tmp_path / "model", "--out", tmp_path / "out", "--device", "cpu", check=False)
    assert proc.returncode == 2 and "OIDN's network" in proc.stderr and str(tmp_path / "model") in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    args = build_parser().parse_args(["gpu-recipe", "--out", "x"])
    assert set(vars(args)) - {"command", "fn"} == {f.name for f in dataclasses.fields(Settings)}


def test_gpu_recipe_dry_run_of_the_oidn_based_model(cleaned, tmp_path):
    """The recipe for a model on OIDN's network: OIDN crop packs, further training of the exported model from
    its own base.tza (no pyoidn needed), the bench at 1 and 3 steps, an output that fits the device tool."""
    from mcdenoise.pipeline.store import Store
    from mcdenoise.train.oidn_pack import crop_pack, ensure_pack, load_pack

    store, _ = cleaned
    keys = [f"store={store}", f"runs={tmp_path / 'runs'}", "diffusion.base=oidn", "diffusion.epochs=1",
            "diffusion.crop=16", "diffusion.batch_size=2", "diffusion.val_frames=1", "diffusion.device=cpu"]
    run("train", "--model", "diffusion", "--spp", "any", *keys)
    run("export", "--spp", "any", "--out", tmp_path / "model", *keys)
    s = Store(store)
    for split, n in (("train", 6), ("val", 2)):
        pack = load_pack(ensure_pack(s, s.frames(split), tmp_path / f"{split}_pack.safetensors", quiet=True))
        crop_pack(pack, tmp_path / f"{split}.safetensors", n, 16, seed=1 if split == "val" else 0)
    out = tmp_path / "out"
    run("gpu-recipe", "--model", tmp_path / "model", "--train", tmp_path / "train.safetensors",
        "--val", tmp_path / "val.safetensors", "--out", out, "--minutes", "0.02",
        "--device", "cpu", "--batch", "2", "--sizes", "32x24", module=("-m", "mcdenoise"))
    files = list(out.iterdir())
    assert len(files) <= 8 and all(f.stat().st_size < 16 * 2**20 for f in files)
    result = json.loads((out / "result.json").read_text())
    assert [b["steps"] for b in result["bench"]] == [1, 3] and all(b["seconds"] > 0 for b in result["bench"])
    assert result["epochs"] >= 1 and result["train_images_per_s"] > 0
    # epoch 0 of the continued run is the exported model itself
    assert result["history"][0]["epoch"] == 0
    assert {"control_fp16.safetensors", "model.json", "report.md"} <= {f.name for f in files}
    # crops whose albedo and normal are not what the model's base reads are refused, naming the crops
    large = tmp_path / "large"
    large.mkdir()
    meta = json.loads((tmp_path / "model" / "model.json").read_text())
    (large / "model.json").write_text(json.dumps({**meta, "base_network": "rt_hdr_calb_cnrm_large"}))
    proc = run("gpu-recipe", "--model", large, "--train", tmp_path / "train.safetensors", "--val",
               tmp_path / "val.safetensors", "--out", tmp_path / "out2", "--device", "cpu", check=False,
               module=("-m", "mcdenoise"))
    assert proc.returncode == 2 and str(tmp_path / "train.safetensors") in proc.stderr and "prefiltered" in proc.stderr
    assert not (tmp_path / "out2").exists() or not any((tmp_path / "out2").iterdir())


def test_gpu_prepare_cuts_crops_with_the_aux_the_models_base_reads(cleaned, tmp_path):
    """A model on OIDN's clean-aux network gets crops whose albedo and normal are prefiltered by OIDN's aux
    networks (the pack its CPU training reads), a model on the standard network the rendered ones."""
    from mcdenoise.train.oidn_pack import load_pack, pack_clean_aux

    store, _ = cleaned
    for network, clean in (("rt_hdr_calb_cnrm_large", True), ("rt_hdr_alb_nrm", False)):
        model = tmp_path / network
        model.mkdir()
        (model / "model.json").write_text(json.dumps({"format": "mcdenoise-oidn-control", "base_network": network}))
        out = tmp_path / f"gpu_{network}"
        run("gpu-prepare", "--model", model, "--out", out, "--no-wheels", "--train-crops", "2", "--val-crops", "1",
            "--side", "16", f"store={store}", f"runs={tmp_path / 'runs'}", "diffusion.base=oidn")
        assert pack_clean_aux(out / "train_crops.safetensors") is clean
        assert pack_clean_aux(out / "val_crops.safetensors") is clean
    # the two differ in their albedo and normal (x's channels 3..8), not in their colour
    a, b = (load_pack(tmp_path / f"gpu_{n}" / "train_crops.safetensors") for n in ("rt_hdr_calb_cnrm_large",
                                                                                  "rt_hdr_alb_nrm"))
    assert bool((a["x"][:, :3] == b["x"][:, :3]).all()) and not bool((a["x"][:, 3:] == b["x"][:, 3:]).all())
