"""Cleaner training, resume, apply and the Isik baseline on a tiny synthetic store (no rendering).

The store (``tests.helpers.make_clean_store``) mimics what the dataset stage writes (dataset.json,
scene.json, frame.json, gt1, gt2 and low-spp stacks): a smooth "true" image per frame, GT1/GT2 =
truth + independent noise, the stacks = truth + stronger noise, every schema buffer present.
"""
import json
import os

import numpy as np
import pytest
import torch

from mcdenoise.clean import apply as clean_apply
from mcdenoise.clean.data import IN_CHANNELS, BaselinePairs, CleanerPairs, crop_and_flip, frame_inputs
from mcdenoise.clean.model import load_model
from mcdenoise.clean.train import (
    baseline_checkpoint,
    gt_clean as cmd_gt_clean,
    run_dir,
    save_best,
    train,
)
from mcdenoise.pipeline.store import Store
from tests.helpers import FRAMES, SCENES, SIZE, make_clean_store, tiny_cfg


@pytest.fixture(scope="module")
def store_root(tmp_path_factory):
    return make_clean_store(tmp_path_factory.mktemp("clean") / "store")


@pytest.fixture
def cfg_dir(tmp_path, store_root):
    os.symlink(store_root, tmp_path / "store")
    return tmp_path


def test_inputs_follow_the_schema(store_root):
    store = Store(store_root)
    inputs, radiance = frame_inputs(store.read_image("s00000", 0, "gt1")[0])
    assert inputs.shape == (IN_CHANNELS, SIZE, SIZE) and radiance.shape == (3, SIZE, SIZE)
    assert np.isfinite(inputs).all()


def test_crop_and_flip_moves_pixels_only():
    a = np.arange(2 * 4 * 4, dtype=np.float32).reshape(2, 4, 4)
    rng = np.random.default_rng(3)
    seen = set()
    for _ in range(20):
        (c,) = crop_and_flip([a], 4, rng)
        seen.add(c.tobytes())
        assert sorted(c.ravel()) == sorted(a.ravel())     # same values: no sign change, only moved
    assert len(seen) == 4                                  # the four flip combinations occur


def test_datasets_give_crops_and_swap(store_root):
    store = Store(store_root)
    keys = store.frames("train")
    ds = CleanerPairs(store, keys, crop=8, crops_per_frame=2, seed=0)
    item = ds[0]
    assert item["inputs"].shape == (IN_CHANNELS, 8, 8) and item["target"].shape == (3, 8, 8)
    val = CleanerPairs(store, keys, crop=None)
    whole = val[0]
    gt2 = store.read_image(keys[0].scene, keys[0].frame, "gt2")[0]["color"]
    np.testing.assert_array_equal(whole["target"].numpy(), np.moveaxis(gt2, 2, 0))


def _mse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))


@pytest.mark.slow
def test_cleaned_gt1_is_closer_to_gt2_than_gt1(cfg_dir):
    """The point of the cleaner (paper section 3.1): C(GT1) nearer an independent GT2 than GT1 is.

    On the tiny store GT1 and GT2 carry independent 10% noise around a smooth truth, so a perfect
    cleaner halves the squared error; ask for a 30% cut on the val frames after 2 epochs.
    """
    cfg = tiny_cfg(cfg_dir, epochs=2)
    train(cfg, "cleaner", quiet=True)
    model, _ = load_model(run_dir(cfg, "cleaner"))
    store = Store(cfg.store)
    before = after = 0.0
    for key in store.frames("val"):
        gt1 = store.read_image(key.scene, key.frame, "gt1")[0]
        gt2 = store.read_image(key.scene, key.frame, "gt2")[0]["color"]
        out = clean_apply.denoise(model, *frame_inputs(gt1), tile=512, device="cpu")
        before += _mse(gt1["color"], gt2)
        after += _mse(out, gt2)
    assert after < 0.7 * before, (after, before)


@pytest.mark.slow
def test_training_reduces_loss_and_writes_files(cfg_dir):
    # Without the range term: the learned affinities alone must learn (with it, the first epoch
    # already starts near the tiny store's optimum and leaves little to see).
    cfg = tiny_cfg(cfg_dir, epochs=4, range_term="false")
    summary = train(cfg, "cleaner", quiet=True)
    folder = run_dir(cfg, "cleaner")
    hist = json.loads((folder / "train.json").read_text())["history"]
    assert len(hist) == 4 and summary["trained_epochs"] == 4
    # Target noise makes single epochs jumpy: compare the end with the first epoch.
    assert hist[-1]["val"]["smape"] < 0.95 * hist[0]["val"]["smape"]
    assert min(h["train_loss"] for h in hist[1:]) < hist[0]["train_loss"]
    assert all(np.isfinite(h["val"]["smape"]) for h in hist)
    assert (folder / "model.safetensors").exists() and (folder / "loss.png").stat().st_size > 1000
    model, meta = load_model(folder)
    assert meta["epoch"] == summary["best"]["epoch"] and meta["hparams"]["in_channels"] == IN_CHANNELS
    # Rerun with the same epochs: nothing to do.
    assert train(cfg, "cleaner", quiet=True)["trained_epochs"] == 0


@pytest.mark.slow
def test_resume_is_exact(tmp_path, store_root):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        d.mkdir()
        os.symlink(store_root, d / "store")
    train(tiny_cfg(a, epochs=2), "cleaner", quiet=True)
    train(tiny_cfg(b, epochs=1), "cleaner", quiet=True)
    summary = train(tiny_cfg(b, epochs=2), "cleaner", quiet=True)
    assert summary["trained_epochs"] == 1
    from safetensors.torch import load_file
    wa = load_file(str(a / "runs" / "cleaner" / "last.safetensors"))
    wb = load_file(str(b / "runs" / "cleaner" / "last.safetensors"))
    assert wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k


def test_changed_settings_refuse_to_resume(cfg_dir):
    train(tiny_cfg(cfg_dir, epochs=1), "cleaner", quiet=True)
    with pytest.raises(RuntimeError, match="different settings.*lr"):
        train(tiny_cfg(cfg_dir, epochs=2, lr=0.1), "cleaner", quiet=True)
    # Another model shape (here: no range term) is the same clear refusal, not a tensor size mismatch.
    with pytest.raises(RuntimeError, match=r"different settings \(hparams\)"):
        train(tiny_cfg(cfg_dir, epochs=2, range_term="false"), "cleaner", quiet=True)


def test_apply_is_idempotent_and_follows_the_checkpoint(cfg_dir):
    cfg = tiny_cfg(cfg_dir, epochs=1)
    assert cmd_gt_clean(cfg, quiet=True) == 0
    store = Store(cfg.store)
    paths = [store.image_path(k.scene, k.frame, "gt_clean") for k in store.frames()]
    assert len(paths) == len(SCENES) * FRAMES and all(p.exists() for p in paths)
    digest = json.loads((store.root / "cleaner.json").read_text())["sha256"]
    key = store.frames()[0]
    img, rec = store.read_image(key.scene, key.frame, "gt_clean")
    assert rec["cleaner_sha256"] == digest and img["color"].shape == (SIZE, SIZE, 3)
    assert np.isfinite(img["color"]).all() and (img["color"] >= 0).all()
    mtimes = [p.stat().st_mtime_ns for p in paths] + [(store.root / "cleaner.json").stat().st_mtime_ns]
    stats = clean_apply.apply_cleaner(cfg, quiet=True)
    assert stats["written"] == 0 and stats["skipped"] == len(paths)
    assert [p.stat().st_mtime_ns for p in paths] + [(store.root / "cleaner.json").stat().st_mtime_ns] == mtimes
    # A changed checkpoint (here: perturbed weights saved as the best) rewrites every frame.
    folder = run_dir(cfg, "cleaner")
    model, meta = load_model(folder)
    with torch.no_grad():
        for p in model.parameters():
            p.mul_(1.01)
    save_best(folder, model, meta)
    stats = clean_apply.apply_cleaner(cfg, quiet=True)
    assert stats["written"] == len(paths)
    assert json.loads((store.root / "cleaner.json").read_text())["sha256"] != digest
    assert store.image_header(key.scene, key.frame, "gt_clean")["cleaner_sha256"] != digest


def test_baseline_trains_from_low_spp(cfg_dir):
    cfg = tiny_cfg(cfg_dir, epochs=1)
    clean_apply_needed = cmd_gt_clean(cfg, quiet=True)
    assert clean_apply_needed == 0
    store = Store(cfg.store)
    ds = BaselinePairs(store, store.frames("train"), spp=4, crop=8, crops_per_frame=1, seed=0)
    item = ds[0]
    assert item["inputs"].shape == (IN_CHANNELS, 8, 8)
    assert train(cfg, mode="baseline", spp=4, quiet=True)["epochs"] > 0
    folder = run_dir(cfg, "baseline", 4)
    assert folder.name == "isik_spp4" and (folder / "model.safetensors").exists()
    meta = json.loads((folder / "model.json").read_text())
    assert meta["mode"] == "baseline" and meta["spp"] == 4


@pytest.mark.slow
def test_baseline_sppany_draws_every_spp_and_serves_them(cfg_dir):
    """SPP=any: one Isik model trained on every sample count the stacks pool (4 and 8 spp for the
    tiny store's two stacks), which the evaluator's lookup finds for a count without its own run
    (tests/test_evaluate.py checks that a per-spp run wins where there is one)."""
    cfg = tiny_cfg(cfg_dir, epochs=1)
    assert cmd_gt_clean(cfg, quiet=True) == 0
    store = Store(cfg.store)
    ds = BaselinePairs(store, store.frames("train"), spp=[4, 8], crop=8, crops_per_frame=4, seed=0)
    seen = []
    read = store.read
    store.read = lambda scene, frame, spp, **kw: seen.append(spp) or read(scene, frame, spp, **kw)
    for i in range(len(ds)):
        ds[i]
    assert sorted(set(seen)) == [4, 8]
    assert train(cfg, mode="baseline", spp="any", quiet=True)["epochs"] > 0
    folder = run_dir(cfg, "baseline", "any")
    meta = json.loads((folder / "model.json").read_text())
    assert folder.name == "isik_sppany" and meta["spp"] == "any" and meta["spp_choices"] == [4, 8]
    assert baseline_checkpoint(cfg, 8) == folder and baseline_checkpoint(cfg, 16) is None


@pytest.mark.slow
def test_clean_report_scores_and_draws(cfg_dir):
    """clean-report: its GT1 and GT_clean rows are the metrics of the stored images against GT2,
    the MSE ratio shows the gain, the crop grid is a picture; the tiny store has no test split,
    which the baseline section says instead of failing."""
    from mcdenoise.clean.report import run_report
    from mcdenoise.pipeline.metrics import all_metrics, mse

    cfg = tiny_cfg(cfg_dir, epochs=2)
    assert cmd_gt_clean(cfg, quiet=True) == 0 and train(cfg, mode="baseline", spp=4, quiet=True)["epochs"] > 0
    out = cfg_dir / "report"
    r = run_report(cfg, out=str(out), spp=4)
    store = Store(cfg.store)
    keys = store.frames("val")
    read = lambda k, n: store.read_image(k.scene, k.frame, n, ["color"])[0]["color"]
    gt1_psnr = np.mean([all_metrics(read(k, "gt1"), read(k, "gt2"))["psnr"] for k in keys])
    ratio = np.mean([mse(read(k, "gt_clean"), read(k, "gt2")) / mse(read(k, "gt1"), read(k, "gt2")) for k in keys])
    assert r["val"]["frames"] == len(keys) == 2
    assert r["val"]["gt1_vs_gt2"]["psnr"] == pytest.approx(gt1_psnr)
    assert r["val"]["mse_ratio_mean"] == pytest.approx(ratio) and ratio < 0.8
    assert 0 < r["val"]["mse_ratio_tonemapped_mean"] < 0.8
    assert r["val"]["clean_vs_gt2"]["psnr"] > r["val"]["gt1_vs_gt2"]["psnr"]
    assert r["training"]["epochs"] == 2 and r["baseline"]["frames"] == 0
    # The untrained-network row (the range term's prior alone) is there and already beats GT1.
    assert r["val"]["untrained_vs_gt2"]["psnr"] > r["val"]["gt1_vs_gt2"]["psnr"]
    md = (out / "cleaner.md").read_text()
    assert f"{ratio:.3f}" in md and "no test frame" in md and "untrained network, range term only" in md
    from PIL import Image
    with Image.open(out / "cleaner_crops.png") as im:
        assert im.size[0] > im.size[1] > 100          # 6 columns by 2 rows
        assert np.asarray(im.convert("L")).std() > 5  # not blank


@pytest.mark.slow
def test_time_budget_stops_after_an_epoch_and_resumes(cfg_dir):
    cfg = tiny_cfg(cfg_dir, epochs=3, time_budget_s="0.000001")
    assert train(cfg, "cleaner", quiet=True)["epochs"] == 1
    assert train(cfg, "cleaner", quiet=True)["epochs"] == 2


@pytest.mark.slow
def test_gt_clean_twice_writes_the_same_bytes(cleaned, tiny_store, tmp_path):
    """Same seeds, same files: ``gt-clean`` run again in a fresh process on the same rendered store trains the
    same cleaner to the byte and writes the same GT_clean pixels (what makes two make demo runs agree; it holds
    for one torch thread count: float sums over another number of threads round differently: README.md)."""
    import shutil

    from tests.helpers import CLEAN_TINY, TINY, assert_same_store, cli

    store, runs = cleaned
    again = tmp_path / "store"
    shutil.copytree(tiny_store[0], again)
    cli("gt-clean", "--config", TINY, f"store={again}", f"runs={tmp_path / 'runs'}", *CLEAN_TINY, "--quiet")
    assert (tmp_path / "runs/cleaner/model.safetensors").read_bytes() == (runs / "cleaner/model.safetensors").read_bytes()
    assert any(again.rglob("gt_clean.exr"))
    assert_same_store(store, again)            # every image, gt_clean included: pixels and header records
