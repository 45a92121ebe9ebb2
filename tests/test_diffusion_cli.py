"""The diffusion stage through the real command line on configs/tiny.yaml: train (also under torchrun with
2 CPU processes), denoise a store frame and a foreign EXR, export, eval and bench, the GPU recipe, and the
errors users meet."""
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
# The shipped model's architecture and recipe (the defaults) at a size that trains in seconds
SMALL = ["diffusion.crop=16", "diffusion.batch_size=2", "diffusion.val_frames=1", "diffusion.warmup_steps=2",
         "diffusion.device=cpu"]

pytestmark = pytest.mark.slow


def run(*args, check=True, module=("-m", "pipeline")):
    proc = subprocess.run([sys.executable, *module, *map(str, args)], cwd=ROOT, capture_output=True, text=True,
                          timeout=900)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr[-4000:]}")
    return proc


@pytest.fixture(scope="module")
def setup(cleaned, tmp_path_factory):
    store, _ = cleaned
    tmp = tmp_path_factory.mktemp("diffusion")
    return tmp, ["--config", TINY, f"store={store}", f"runs={tmp / 'runs'}", *SMALL]


def test_train_then_denoise(setup, tmp_path):
    tmp, keys = setup
    proc = run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=2")
    assert "diffusion_spp4: 2 epochs (2 this run" in proc.stdout and "val PSNR" in proc.stdout
    folder = tmp / "runs" / "diffusion_spp4"
    meta = json.loads((folder / "model.json").read_text())
    # the shipped kind: a Control Module on OIDN's final-frame network
    assert meta["format"] == "mcdenoise-oidn-control" and meta["base_network"] == "rt_hdr_calb_cnrm_large"
    assert meta["spp"] == [4] and (folder / "loss.png").exists() and (folder / "last.safetensors").exists()
    # A second run with the same epochs does nothing.
    assert "already trained" in run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=2").stdout

    store = Path(keys[2].split("=", 1)[1])
    scene = sorted(p.name for p in (store / "scenes").iterdir())[0]
    out = tmp_path / "den.exr"
    run("denoise", "--spp", "4", "--frame", f"{scene}/000", "--out", out, "--steps", "3", "--samples", "3", *keys)
    img, rec = read_image(out)
    assert img["color"].shape == (24, 32, 3) and np.isfinite(img["color"]).all()
    assert rec["method"] == "ours" and rec["steps"] == 3 and rec["samples"] == 3 and rec["layers"] == ["std"]
    assert (_layer(out, "std") >= 0).all()
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
               "diffusion.epochs=1", "diffusion.base_network=rt_hdr_alb_nrm", module=("-m", "torch.distributed.run"))
    assert proc.returncode == 0 and (tmp / "ddp" / "diffusion_spp4" / "control.safetensors").exists()


def test_errors_are_one_line_and_exit_2(setup, tmp_path):
    tmp, keys = setup
    proc = run("train", "--model", "diffusion", "--spp", "4", "--config", TINY, f"store={tmp_path / 'none'}",
               check=False)
    assert proc.returncode == 2 and "no dataset" in proc.stderr
    proc = run("denoise", "--spp", "16", "--frame", "s00000/000", "--out", tmp_path / "x.exr", *keys,
               f"runs={tmp_path / 'empty'}", "diffusion.shipped=false", check=False)   # no run, no shipped fallback
    assert proc.returncode == 2 and "no diffusion checkpoint" in proc.stderr
    assert not (tmp_path / "x.exr").exists()
    proc = run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.base=/nonexistent", check=False)
    assert proc.returncode == 2 and "diffusion.base" in proc.stderr and "Traceback" not in proc.stderr
    proc = run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.skip=27", check=False)
    assert proc.returncode == 2 and "diffusion.skip" in proc.stderr
    proc = run("pretrain", *keys, check=False)                               # retired: not a command
    assert proc.returncode == 2 and "invalid choice: 'pretrain'" in proc.stderr


def test_a_run_resumes_only_with_its_epoch_steps(setup, tmp_path):
    tmp, keys = setup
    keys = [k for k in keys if not str(k).startswith("runs=")] + [f"runs={tmp_path / 'runs'}"]
    run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=1", "diffusion.epoch_steps=1",
        "diffusion.base_network=rt_hdr_alb_nrm")
    proc = run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=1", "diffusion.epoch_steps=2",
               "diffusion.base_network=rt_hdr_alb_nrm", check=False)
    assert proc.returncode == 2 and "epoch_steps" in proc.stderr


def test_eval_runs_the_trained_model_and_says_so(setup, tmp_path):
    """The evaluator loads the run just trained (not the shipped model) and its table says which weights."""
    tmp, keys = setup
    run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=2")
    run("eval", *keys, "eval.methods=[noisy,ours,ours_s3_k2,base_only_s1]", "eval.metrics=[l1,psnr]",
        "eval.equal_time=none", "eval.split=train", "eval.frames=1", f"eval.out={tmp_path / 'rep'}", "--spp", "4")
    md = (tmp_path / "rep" / "eval.md").read_text()
    assert "not available" not in md, md
    header = next(line for line in md.splitlines() if line.startswith("| method"))
    col = header.split(" | ").index("weights")
    for name in ("ours", "ours_s3_k2", "base_only_s1"):
        row = next(line for line in md.splitlines() if line.startswith("|") and f"(`{name}`)" in line)
        l1, psnr_db = (float(c.strip(" *")) for c in row.split("|")[2:4])
        assert 0 <= l1 < 6 and 0 < psnr_db < 100, row
        assert row.split(" | ")[col].startswith(str(tmp / "runs" / "diffusion_spp4")), row
        assert "OIDN rt_hdr_calb_cnrm_large" in row.split(" | ")[col]
    rows = json.loads((tmp_path / "rep" / "eval.json").read_text())["groups"]["train"]["spp"]["4"]["methods"]
    u = rows["ours_s3_k2"]["uncertainty"]            # the mean of 2 samples carries their spread
    assert u["frames"] == 1 and u["calibration"] and all(b["std"] >= 0 and b["rmse"] >= 0 for b in u["calibration"])


def test_bench_denoise_times_ours_its_base_and_oidn(setup, tmp_path):
    tmp, keys = setup
    run("bench-denoise", *keys, "--sizes", "32x32,48x32", "--repeats", "1", "--out", tmp_path)
    result = json.loads((tmp_path / "denoise.json").read_text())
    assert [r["size"] for r in result["rows"]] == ["32x32", "48x32"] and result["precision"] == "fp32"
    for r in result["rows"]:
        assert all(r[k] > 0 for k in ("ours_1step_s", "ours_3step_s", "base_s", "ours_network_s", "base_network_s",
                                      "ours_network_nhwc_s", "base_network_nhwc_s", "oidn_prefilter_s", "oidn_s",
                                      "averaging_s", "filter_s", "filter_both_s"))
        assert r["ours_over_oidn_prefilter"] == round(r["ours_1step_s"] / r["oidn_prefilter_s"], 2)
    g = result["gflop_per_megapixel"]
    assert g["ours"] > g["base"] > 0
    md = (tmp_path / "denoise.md").read_text()
    assert "| 48x32 |" in md and f"ours {g['ours']} GFLOP, its base {g['base']} GFLOP" in md
    bad = run("bench-denoise", *keys, "--sizes", "32by32", "--out", tmp_path, check=False)
    assert bad.returncode == 2 and "WxH" in bad.stderr


def test_export_serves_as_the_shipped_model(setup, tmp_path, monkeypatch):
    """An exported run is what a config without runs of its own falls back to; diffusion.shipped=false turns
    the fallback off; its card's commands make the model again."""
    import mcdenoise.train.model as tm
    from mcdenoise.pipeline.config import load_config

    tmp, keys = setup
    run("train", "--model", "diffusion", "--spp", "4", *keys, "diffusion.epochs=2")
    out = tmp_path / "moved" / "shipped"
    run("export", "--spp", "4", "--out", out, *keys)
    card = (out / "README.md").read_text()
    train_line = next(line for line in card.splitlines() if line.startswith("python -m pipeline train --model diffusion"))
    assert all(k in train_line for k in cfg_overrides(keys))
    data_line = next(line for line in card.splitlines() if line.startswith("python -m pipeline dataset"))
    assert "diffusion." not in data_line   # the data's keys, only them
    monkeypatch.setattr(tm, "SHIPPED_MODEL", out)
    overrides = [k for k in cfg_overrides(keys) if not k.startswith("runs=")] + [f"runs={tmp_path / 'none'}"]
    assert tm.find_run(load_config(TINY, overrides), 16) == out
    with pytest.raises(Exception, match="no diffusion checkpoint"):
        tm.find_run(load_config(TINY, [*overrides, "diffusion.shipped=false"]), 16)


def cfg_overrides(keys):
    return [str(k) for k in keys if "=" in str(k)]
