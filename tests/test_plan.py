"""The cost model (``python -m pipeline plan``): arithmetic from the schema and the config, the
table printed before anything runs, calibration on a real store, and the measuring code on a
miniature case."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.store import Store
from mcdenoise.render.plan import MEASURED, calibrate_from_store, estimate, measure, raw_bytes_per_pixel
from tests.helpers import TINY, cli

PAPER = "configs/paper.yaml"


def test_bytes_per_pixel_follow_the_schema():
    # 6 radiance buffers x 3 float32 + depth float32, 9 half feature channels, 28 float32 variances.
    assert raw_bytes_per_pixel() == (6 * 3 + 1) * 4 + (3 + 3 + 1 + 1 + 1) * 2 + 28 * 4 == 206
    assert raw_bytes_per_pixel(omit=("emission",)) == 206 - 3 * 4 - 3 * 4
    assert sum(b.size for b in schema.BUFFERS) * 2 == len(schema.exr_channel_map())


def test_paper_config_totals():
    cfg = load_config(PAPER, ["render.encoding=exact"])   # the encoding the measured ratios were taken with
    est = estimate(cfg)
    assert est["frames"] == (5650 + est["stress_scenes"]) * 8 and est["stress_scenes"] >= 7
    assert est["samples_per_frame"] == 256 * 256 * (2 * 4096 + 16 * 4)
    gt, stacks = est["parts"]["gt"], est["parts"]["stacks"]
    px = 256 * 256
    cost, overhead = est["seconds_per_sample"], est["overhead_s"]
    write = MEASURED["write_s_per_mpx"] * px / 1e6
    assert gt["core_s"] == pytest.approx(2 * (overhead + px * 4096 * cost + write))
    assert stacks["bytes"] == pytest.approx(16 * px * 206 * MEASURED["zip_ratio"]["stack"])
    assert est["total_core_h"] == pytest.approx(est["frame_core_s"] * est["frames"] / 3600)
    assert est["total_bytes"] == pytest.approx(est["frame_bytes"] * est["frames"])
    # Ground truths dominate compute, stacks dominate disk.
    assert gt["core_s"] > 20 * stacks["core_s"] and stacks["bytes"] > 5 * gt["bytes"]


def test_cost_grows_with_spp_depth_and_resolution():
    base = load_config(None, ["dataset.gt_spp=1024"])
    e = estimate(base)["parts"]["gt"]["core_s"]
    assert estimate(load_config(None, ["dataset.gt_spp=2048"]))["parts"]["gt"]["core_s"] == pytest.approx(2 * e, rel=0.05)
    assert estimate(load_config(None, ["render.max_depth=4"]))["parts"]["gt"]["core_s"] < e
    assert estimate(load_config(None, ["render.max_depth=12"]))["parts"]["gt"]["core_s"] > e
    big = estimate(load_config(None, ["dataset.resolution=[256, 256]"]))
    assert big["parts"]["gt"]["core_s"] == pytest.approx(4 * e, rel=0.15)
    assert big["frame_bytes"] == pytest.approx(4 * estimate(base)["frame_bytes"], rel=0.01)


@pytest.mark.slow
def test_cli_prints_the_table_and_writes_nothing(tmp_path):
    proc = cli("plan", "--config", PAPER, f"store={tmp_path / 'never'}", "--workers", "1,64")
    out = proc.stdout
    assert "5650 scenes" in out and "256x256" in out and "| GT (2 x 4096 spp) |" in out
    assert "| **all** |" in out and "core-h" in out and "GB" in out
    assert "| 64 |" in out and "| 16 |" not in out
    assert not (tmp_path / "never").exists()
    bad = cli("plan", "--config", PAPER, "--workers", "many", check=False)
    assert bad.returncode == 2 and "--workers 'many'" in bad.stderr


@pytest.mark.slow
def test_calibration_on_a_rendered_store(tiny_store):
    root, _ = tiny_store
    c = calibrate_from_store(root)
    assert "calibrated on 6 frames" in c["source"]
    store = Store(root)
    recs = [store.frame_record(k.scene, k.frame) for k in store.frames()]
    gt_bytes = np.mean([r["images"][g]["bytes"] for r in recs for g in ("gt1", "gt2")])
    assert c["zip_ratio"]["gt"] * 206 * 32 * 24 == pytest.approx(gt_bytes, rel=1e-6)
    est = estimate(load_config(TINY), c)
    actual = np.mean([r["bytes"] for r in recs])
    assert est["frame_bytes"] - est["parts"]["gt_clean"]["bytes"] == pytest.approx(actual, rel=0.01)
    proc = cli("plan", "--config", TINY, "--store", root)
    assert "calibrated on 6 frames" in proc.stdout


def test_uncalibrated_disk_estimate_is_near_a_real_store(tiny_store):
    """The measured ZIP ratios (256² and 128² frames) predict the tiny store's bytes within 50 %."""
    root, _ = tiny_store
    store = Store(root)
    actual = np.mean([store.frame_record(k.scene, k.frame)["bytes"] for k in store.frames()])
    est = estimate(load_config(TINY))
    predicted = est["parts"]["gt"]["bytes"] + est["parts"]["stacks"]["bytes"]
    assert 1 / 1.5 < predicted / actual < 1.5


def test_calibrating_on_an_empty_store_is_a_clear_error(tmp_path):
    Store(tmp_path).write_manifest({"scenes": [], "splits": {}})
    proc = cli("plan", "--config", TINY, "--store", tmp_path, check=False)
    assert proc.returncode == 2 and "no rendered frame with render times" in proc.stderr


def test_measure_gives_constants_the_model_uses():
    cfg = load_config(TINY)
    c = measure(cfg, resolutions=(16,), depths=(2, 4), spps=(1, 8), scenes=1, gt_spp=8, repeats=1)
    assert set(c["render"]["16"]) == {"2", "4"}
    assert all(v["rate"] > 0 and v["overhead_s"] >= 0 for v in c["render"]["16"].values())
    assert all(0 < r < 2 for r in c["zip_ratio"].values())
    est = estimate(cfg, c)
    assert math.isfinite(est["frame_core_s"]) and est["frame_core_s"] > 0


def test_fit_survives_timing_noise():
    from mcdenoise.render.plan import _fit
    a, b = _fit([(100, 0.020), (800, 0.015)])    # the larger render measured faster: noise
    assert a == 0.0 and b > 0
    a, b = _fit([(100, 0.010), (800, 0.080)])
    assert b == pytest.approx(1e-4) and a == pytest.approx(0.0, abs=1e-9)


@pytest.mark.slow
def test_progressive_gt_uses_the_expected_spp_from_the_target():
    """Every GT of a (synthetic) measured distribution estimates 48 dB at 1024 spp: a 45 dB target needs
    1024·10^(-0.3) = 513.2 spp, i.e. 9 whole passes of 64 (576 spp), each pass with its overhead."""
    c = {**MEASURED, "gt_psnr": {"spp": 1024, "quantiles": [48.0] * 20}}
    fixed = estimate(load_config(None, ["dataset.gt_spp=576"]), c)
    prog = estimate(load_config(None, ["dataset.gt_target_psnr=45", "dataset.gt_pass_spp=64",
                                       "dataset.gt_max_spp=1024"]), c)
    g = prog["parts"]["gt"]
    assert (g["spp"], g["passes"]) == (576, 9)
    assert g["core_s"] == pytest.approx(fixed["parts"]["gt"]["core_s"] + 2 * 8 * prog["overhead_s"])
    assert prog["samples_per_frame"] == fixed["samples_per_frame"]
    capped = estimate(load_config(None, ["dataset.gt_target_psnr=60", "dataset.gt_max_spp=2048"]), c)
    assert capped["parts"]["gt"]["spp"] == 2048
    assert "target 45 dB" in cli("plan", "dataset.gt_target_psnr=45").stdout


def test_scene_kinds_weigh_the_cost_per_sample_by_their_probability():
    """Interiors and product shots cost kind_cost times an objects scene per sample; a config's random scenes the
    mean over its kind probabilities, the stress presets as objects scenes; configs without the keys as before."""
    c = {**MEASURED, "kind_cost": {"interior": 2.0, "product": 5.0}}
    base = ["dataset.stress=[]"]
    plain = estimate(load_config(None, base), c)
    assert plain["kind_factor"] == 1.0
    rooms = estimate(load_config(None, base + ["scene.interior_probability=0.5", "scene.product_probability=0.2"]), c)
    # 50 % interiors, 0.5 x 0.2 = 10 % products, 40 % objects
    assert rooms["kind_factor"] == pytest.approx(0.5 * 2 + 0.1 * 5 + 0.4)
    assert rooms["seconds_per_sample"] == pytest.approx(1.9 * plain["seconds_per_sample"])
    with_stress = estimate(load_config(None, ["scene.interior_probability=1", "dataset.stress=[all]"]), c)
    n, k = with_stress["scenes"], with_stress["stress_scenes"]
    assert k > 0 and with_stress["seconds_per_sample"] == pytest.approx(
        plain["seconds_per_sample"] * (2.0 * n + k) / (n + k))


def test_measure_kinds_gives_each_kind_over_objects_scenes():
    from mcdenoise.render.plan import measure_kinds
    cfg = load_config(TINY, ["render.max_depth=4"])
    costs = measure_kinds(cfg, scenes=1, res=16, spps=(2, 8))
    assert set(costs) == {"interior", "product"} and all(v > 0 for v in costs.values())
