"""Progressive ground truth (render.progressive): the error estimate, the stop rule, pooling passes,
and the dataset stage with dataset.gt_target_psnr on configs/tiny.yaml."""
import json
import math

import numpy as np
import pytest

from mcdenoise.pipeline import metrics
from mcdenoise.pipeline.store import Store
from mcdenoise.render.buffers import RenderResult
from mcdenoise.render.progressive import StopRule, estimated_psnr, expected_spp, pass_seed, render_to_target
from tests.helpers import TINY, assert_same_store, cli


def test_estimated_psnr_matches_the_error_of_simulated_means():
    """Means of n noisy samples around a known image: their measured PSNR against it is what the
    estimate predicts from the means and their variance alone."""
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.0, 4.0, size=(64, 64, 3))
    n, sigma = 256, 0.8 * truth + 0.05
    samples = truth + sigma * rng.standard_normal((n, *truth.shape))
    mean, var = samples.mean(0), samples.var(0, ddof=1) / n
    assert estimated_psnr(mean, var) == pytest.approx(metrics.psnr(mean, truth), abs=0.15)


class _TwoPointPasses:
    """A fake renderer: each pass of n (even) samples per pixel has half of them at c + s and half at
    c - s. All N samples pooled: mean c, unbiased variance s²·N/(N-1), so the variance of the mean is
    s²/(N-1) exactly, and the estimated PSNR after N samples is 10·log10((N-1)·(1+c)^4 / s²)."""

    def __init__(self, c, s):
        self.c, self.s, self.seeds = c, s, []

    def __call__(self, spp, seed):
        self.seeds.append(seed)
        var = np.full((4, 5, 3), self.s ** 2 / (spp - 1), np.float32)   # s²·n/(n-1) / n
        return RenderResult({"color": np.full((4, 5, 3), self.c, np.float32), "color.variance": var},
                            seconds=0.0)


@pytest.mark.parametrize("target,cap,want", [(30.0, 1024, 256),   # 4·(N-1) >= 1000 first at N = 256
                                             (30.0, 128, 128),    # the cap comes first
                                             (10.0, 1024, 16)])   # the first pass is already enough
def test_stop_rule_on_a_known_variance(target, cap, want):
    # c = 1, s = 2: (1+c)^4/s² = 4, so PSNR(N) = 10·log10(4·(N-1)).
    fake = _TwoPointPasses(1.0, 2.0)
    r = render_to_target(fake, 1234, StopRule(target, 16, cap))
    assert r.spp == want and r.passes == want // 16 == len(fake.seeds)
    assert r.estimated_psnr == pytest.approx(10 * math.log10(4 * (want - 1)), abs=1e-4)
    assert [s for s, _ in r.history] == list(range(16, want + 1, 16))
    assert fake.seeds[0] == 1234 and len(set(fake.seeds)) == len(fake.seeds)
    # The planner's prediction from the estimate at one pass agrees (up to the n-1 of the variance).
    assert expected_spp(r.history[0][1], 16, StopRule(target, 16, cap)) in (want, want + 16)


def test_no_target_is_one_render_of_gt_spp():
    fake = _TwoPointPasses(0.5, 1.0)
    r = render_to_target(fake, 99, StopRule(None, 64, 1024))
    assert (r.spp, r.passes, fake.seeds) == (1024, 1, [99])


def test_pass_seeds_are_deterministic_and_distinct():
    seeds = [pass_seed(s, k) for s in range(200) for k in range(64)]
    assert seeds == [pass_seed(s, k) for s in range(200) for k in range(64)]
    assert len(set(seeds)) == len(seeds) and all(0 <= s < 2 ** 32 for s in seeds)


@pytest.mark.slow
def test_progressive_render_matches_one_render_of_the_total():
    """On a real scene, 4 passes of 16 spp pooled vs one render of 64 spp: the same estimator, so the
    two means differ by their combined noise only and the variances of the mean agree."""
    from mcdenoise.pipeline.config import load_config
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba
    from mcdenoise.render.buffers import needed_features, render_image
    from mcdenoise.render.dataset import make_plan
    from mcdenoise.render.scene import build_scene, build_sensor

    cfg = load_config(TINY)
    mi = import_mitsuba(cfg.render.variant, 0)
    desc = make_plan(cfg).scenes[0]["description"]
    scene = build_scene(mi, desc)
    sensor = build_sensor(mi, desc, 0, 48, 40)
    feats = needed_features(mi, scene)

    def render_pass(spp, seed):
        return render_image(mi, scene, sensor, spp=spp, seed=seed, features=feats, max_depth=5, rr_depth=5)

    prog = render_to_target(render_pass, 5, StopRule(1e9, 16, 64))   # an unreachable target: runs to the cap
    one = render_pass(64, 77)
    assert prog.spp == 64 and prog.passes == 4
    a, b = prog.buffers, one.buffers
    var = a["color.variance"].astype(np.float64) + b["color.variance"]
    noisy = var > 0
    z2 = (a["color"] - b["color"]).astype(np.float64)[noisy] ** 2 / var[noisy]
    assert 0.7 < z2.mean() < 1.4, z2.mean()   # E[z²] = 1 when both are unbiased with the stated variance
    ratio = np.median(a["color.variance"][noisy]) / np.median(b["color.variance"][noisy])   # robust to fireflies
    assert 0.8 < ratio < 1.25, ratio
    again = render_to_target(render_pass, 5, StopRule(1e9, 16, 64))
    for key in a:
        np.testing.assert_array_equal(again.buffers[key], a[key], err_msg=key)


PROGRESSIVE = ["dataset.gt_target_psnr=30", "dataset.gt_pass_spp=16", "dataset.gt_max_spp=128"]


@pytest.fixture(scope="module")
def progressive_store(tmp_path_factory):
    root = tmp_path_factory.mktemp("progressive") / "store"
    cli("dataset", "--config", TINY, f"store={root}", *PROGRESSIVE, "--quiet")
    return root


@pytest.mark.slow
def test_dataset_records_spp_estimate_and_gt_psnr(progressive_store):
    store = Store(progressive_store)
    reached = []
    for key in store.frames():
        sm = store.scene_manifest(key.scene)
        assert (sm["gt_spp"], sm["gt_target_psnr"], sm["gt_pass_spp"]) == (128, 30.0, 16)
        rec = store.frame_record(key.scene, key.frame)
        gt = rec["gt"]
        for name in ("gt1", "gt2"):
            spp, est = gt["spp"][name], gt["estimated_psnr"][name]
            assert spp % 16 == 0 and 16 <= spp <= 128 and (est >= 30.0 or spp == 128)
            assert rec["images"][name]["spp"] == spp and rec["images"][name]["passes"] == spp // 16
            reached.append(spp)
        g1 = store.read_image(key.scene, key.frame, "gt1", ["color"])[0]["color"]
        g2 = store.read_image(key.scene, key.frame, "gt2", ["color"])[0]["color"]
        assert gt["psnr_gt1_gt2"] == pytest.approx(metrics.psnr(g1, g2), abs=1e-3)
        assert sm["rendered"][str(key.frame)]["gt"] == gt
    assert len(set(reached)) > 1, "every GT stopped at the same spp: the test does not exercise the rule"
    assert cli("verify", progressive_store).returncode == 0
    report = json.loads(cli("inspect", progressive_store, "--json").stdout)
    assert report["gt"]["frames"] == 6 and report["gt"]["spp_max"] <= 128
    assert "GT1 vs GT2" in cli("inspect", progressive_store).stdout


@pytest.mark.slow
def test_progressive_frame_resumes_to_the_identical_images(progressive_store, tmp_path):
    """A frame that lost its GT2 and frame.json (killed mid-frame) re-renders GT2 pass by pass to the
    same pixels, spp and seeds."""
    import shutil

    copy = tmp_path / "store"
    shutil.copytree(progressive_store, copy)
    key = Store(copy).frames()[0]
    (Store(copy).frame_dir(key.scene, key.frame) / "frame.json").unlink()
    Store(copy).image_path(key.scene, key.frame, "gt2").unlink()
    cli("dataset", "--config", TINY, f"store={copy}", *PROGRESSIVE, "--quiet")
    assert_same_store(progressive_store, copy)
    before = Store(progressive_store).frame_record(key.scene, key.frame)["gt"]
    assert Store(copy).frame_record(key.scene, key.frame)["gt"] == before


def test_plan_calibrates_the_gt_error_distribution_on_the_store(progressive_store):
    from mcdenoise.render.plan import calibrate_from_store

    c = calibrate_from_store(progressive_store)
    store = Store(progressive_store)
    at_1024 = [g["estimated_psnr"][n] + 10 * math.log10(1024 / g["spp"][n])
               for key in store.frames() for g in [store.frame_record(key.scene, key.frame)["gt"]] for n in g["spp"]]
    assert c["gt_psnr"]["spp"] == 1024 and len(c["gt_psnr"]["quantiles"]) == 20
    assert np.median(c["gt_psnr"]["quantiles"]) == pytest.approx(np.median(at_1024), abs=0.5)
    assert "12 GTs" in c["gt_psnr"]["source"]


@pytest.mark.parametrize("override,message", [
    ("dataset.gt_target_psnr=fast", "dataset.gt_target_psnr: expected float"),
    ("dataset.gt_pass_spp=1", "dataset.gt_pass_spp: must be >= 2"),
    ("dataset.gt_max_spp=100", "dataset.gt_max_spp: must be a multiple of gt_pass_spp"),
])
def test_bad_progressive_settings_are_refused(override, message):
    from mcdenoise.pipeline.config import load_config
    from mcdenoise.pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match=message):
        load_config(TINY, ["dataset.gt_target_psnr=40", "dataset.gt_pass_spp=16", override])


@pytest.mark.parametrize("pass_spp", [48, "x"])
def test_verify_flags_gt_spp_that_are_not_whole_passes(progressive_store, tmp_path, pass_spp):
    import shutil

    copy = tmp_path / "store"
    shutil.copytree(progressive_store, copy)
    store = Store(copy)
    for scene in store.scenes():
        store.write_scene_manifest(scene, {**store.scene_manifest(scene), "gt_pass_spp": pass_spp})
    proc = cli("verify", copy, "--headers-only", check=False)
    assert proc.returncode != 0
    assert f"scene.json says a multiple of gt_pass_spp {pass_spp!r} up to 128" in proc.stdout + proc.stderr
