"""Confidence intervals, paired bootstrap and the generated headline, on cases with a known answer."""
import math

import numpy as np
import pytest

from mcdenoise.evaluate.compare import annotate
from mcdenoise.evaluate.headline import headline, leader_phrases
from mcdenoise.evaluate.stats import MIN_FRAMES, lead, mean_ci, paired_bootstrap, significant

# ---- paired bootstrap ------------------------------------------------------------------------


def test_constant_difference_gives_a_zero_width_interval_at_that_value():
    a = np.random.default_rng(0).normal(40, 3, size=16)       # frames differ a lot; the difference never does
    got = paired_bootstrap(a + 0.75, a, resamples=2000, seed=1)
    assert got["diff"] == pytest.approx(0.75)
    assert got["lo"] == pytest.approx(0.75) and got["hi"] == pytest.approx(0.75)
    assert got["n"] == 16 and significant(got)


def test_independent_noise_interval_covers_zero_about_95_percent_of_the_time():
    # Two methods that are the same up to independent per-frame noise: the true mean difference is 0.
    n_trials, frames = 300, 30
    covered = 0
    for trial in range(n_trials):
        rng = np.random.default_rng(1000 + trial)
        shared = rng.normal(35, 4, size=frames)              # frame difficulty, common to both
        a, b = shared + rng.normal(0, 1, frames), shared + rng.normal(0, 1, frames)
        got = paired_bootstrap(a, b, resamples=2000, seed=trial)
        covered += got["lo"] <= 0 <= got["hi"]
    assert 0.90 <= covered / n_trials <= 0.99


def test_pairing_detects_a_small_shift_that_frame_spread_hides():
    rng = np.random.default_rng(3)
    shared = rng.normal(35, 5, size=20)
    a, b = shared + 0.5 + rng.normal(0, 0.1, 20), shared + rng.normal(0, 0.1, 20)
    assert significant(paired_bootstrap(a, b, resamples=2000, seed=0))
    # unpaired, the two means' intervals overlap almost entirely
    ca, cb = mean_ci(a), mean_ci(b)
    assert ca["lo"] < cb["hi"] and cb["lo"] < ca["hi"]


def test_bootstrap_is_reproducible_with_its_seed():
    rng = np.random.default_rng(5)
    a, b = rng.normal(0, 1, 16), rng.normal(0.2, 1, 16)
    first = paired_bootstrap(a, b, resamples=3000, seed=11)
    assert paired_bootstrap(a, b, resamples=3000, seed=11) == first
    other = paired_bootstrap(a, b, resamples=3000, seed=12)
    assert other["diff"] == first["diff"] and (other["lo"], other["hi"]) != (first["lo"], first["hi"])


def test_too_few_frames_or_non_finite_values_give_no_interval():
    few = paired_bootstrap([1.0] * (MIN_FRAMES - 1), [0.0] * (MIN_FRAMES - 1))
    assert few["diff"] == 1.0 and few["lo"] is None and not significant(few)
    inf = paired_bootstrap([math.inf] + [1.0] * 15, [0.0] * 16)
    assert inf["diff"] is None and inf["lo"] is None and not significant(inf)
    with pytest.raises(ValueError, match="same frames"):
        paired_bootstrap([1.0, 2.0], [1.0])


# ---- mean and its t interval -----------------------------------------------------------------


def test_mean_ci_covers_the_true_mean_about_95_percent_of_the_time():
    hits = 0
    for trial in range(400):
        x = np.random.default_rng(trial).normal(10, 2, size=8)
        ci = mean_ci(x)
        hits += ci["lo"] <= 10 <= ci["hi"]
    assert 0.92 <= hits / 400 <= 0.98


def test_mean_ci_edge_cases():
    assert mean_ci([3.0, 3.0, 3.0]) == {"mean": 3.0, "lo": 3.0, "hi": 3.0, "n": 3}
    assert mean_ci([2.0])["lo"] is None and mean_ci([2.0])["mean"] == 2.0
    one_inf = mean_ci([math.inf, 40.0])
    assert one_inf["mean"] == math.inf and one_inf["lo"] is None


# ---- leads and the headline ------------------------------------------------------------------


def test_lead_follows_the_metric_direction():
    frames = {f"s/{i:03d}": i for i in range(10)}
    low = {f: 0.01 + 0.001 * i for f, i in frames.items()}
    high = {f: v + 0.005 for f, v in low.items()}
    got = lead({"a": high, "b": low}, higher_is_better=False, resamples=1000)
    assert got["best"] == "b" and got["runner_up"] == "a" and got["significant"]
    assert got["diff"] == pytest.approx(-0.005)
    assert lead({"a": high, "b": low}, higher_is_better=True, resamples=1000)["best"] == "a"


def test_a_copy_of_the_leader_is_named_with_it_not_as_its_runner_up():
    """A model that returns another method's output scores the same up to float32 round-off: the
    headline must not call it 'best, not significantly ahead of' the method it copies."""
    frames = {f"s/{i:03d}": 30.0 + i for i in range(8)}
    copy = {f: v * (1 + 3e-7 * (-1) ** i) for i, (f, v) in enumerate(frames.items())}
    worse = {f: v - 0.5 for f, v in frames.items()}
    got = lead({"oidn": frames, "ours": copy, "isik": worse}, higher_is_better=True, resamples=500)
    assert {got["best"], *got["tied"]} == {"oidn", "ours"} and got["runner_up"] == "isik" and got["significant"]
    close = {f: v + 0.01 for f, v in frames.items()}   # a real (if small) difference is not a tie
    assert lead({"a": frames, "b": close}, higher_is_better=True, resamples=500)["tied"] == []
    text = leader_phrases({"psnr": got}, ["psnr"])[0]
    assert "(identical scores: `" in text and "significantly ahead of `isik`" in text


def _rows(values: dict[str, list[float]], metric: str) -> dict:
    return {n: {"label": n, "available": True, "per_frame": [{"frame": f"s{i // 2:05d}/{i % 2:03d}",
                                                                "metrics": {metric: v}} for i, v in enumerate(vals)]}
            for n, vals in values.items()}


def synthetic_result(frames: int = 16) -> dict:
    """Two metrics at 4 spp: isik leads PSNR by a clear 1 dB; oidn leads L1 by a hair that the
    per-frame noise swamps; the noisy input has the best SSIM-like column but is not a denoiser.
    At 16 spp `ours` is missing."""
    rng = np.random.default_rng(0)
    base = rng.normal(38, 3, frames)
    psnr = {"noisy": base - 8, "oidn": base + rng.normal(0, 0.2, frames),
            "isik": base + 1 + rng.normal(0, 0.2, frames)}
    wiggle = np.array([-0.0105, 0.0095] * (frames // 2))    # mean −0.0005, spread 0.01
    l1_base = rng.uniform(0.02, 0.05, frames)
    l1 = {"noisy": l1_base * 3, "oidn": l1_base + wiggle, "isik": l1_base}
    entry4 = {"methods": {}, "equal_time": {}}
    for name in psnr:
        row = _rows({name: psnr[name]}, "psnr")[name]
        for p, v in zip(row["per_frame"], l1[name]):
            p["metrics"]["l1"] = v
        row["metrics"] = {"psnr": float(np.mean(psnr[name])), "l1": float(np.mean(l1[name]))}
        entry4["methods"][name] = row
    entry4["methods"]["ours"] = {"label": "ours", "available": True, "per_frame": []}   # ran, no frame scored
    mc = _rows({"mc": base + 3}, "psnr")["mc"]
    for p in mc["per_frame"]:
        p["metrics"]["l1"] = 0.01
    mc["metrics"] = {"psnr": float(np.mean(base + 3)), "l1": 0.01}
    entry4["equal_time"]["isik"] = mc
    entry16 = {"methods": {n: dict(r) for n, r in entry4["methods"].items()}, "equal_time": {}}
    entry16["methods"]["ours"] = {"label": "ours", "available": False, "reason": "no checkpoint"}
    for entry in (entry4, entry16):
        annotate(entry, ["l1", "psnr"], resamples=2000, seed=0)
    return {"metrics": ["l1", "psnr"],
            "groups": {"test": {"frames": [p["frame"] for p in entry4["methods"]["oidn"]["per_frame"]],
                                "spp": {"4": entry4, "16": entry16, "64": {"skipped": "not in the store"}}}}}


def test_headline_names_the_winner_and_whether_its_lead_is_significant():
    result = synthetic_result()
    leads = result["groups"]["test"]["spp"]["4"]["leads"]
    assert leads["psnr"]["best"] == "isik" and leads["psnr"]["significant"]
    assert leads["l1"]["best"] == "oidn" and not leads["l1"]["significant"]
    text = headline(result)
    assert text.startswith("**Headline** (`test`, 16 frames")
    assert ("At 4 spp the best denoiser is `oidn` on L1 (not significantly ahead of `isik`); "
            "`isik` on PSNR (significantly ahead of `oidn`)") in text
    assert "plain MC at equal time to `isik` has a higher PSNR than every denoiser" in text
    assert "not available: `ours`" in text.split("At 16 spp")[1]
    assert "At 64 spp: not evaluated (not in the store)" in text
    assert "`noisy` on" not in text


def test_headline_lists_hard_case_groups_apart():
    result = synthetic_result()
    result["groups"]["stress"] = {**result["groups"]["test"], "frames": ["stress_x/000"] * 16}
    text = headline(result)
    main, hard = text.split("Hard cases")
    assert "stress" not in main
    assert "On `stress` (16 frames), best: 4 spp: `oidn` on L1; `isik` on PSNR*. 16 spp:" in hard


def test_headline_says_untested_below_min_frames_or_with_inf():
    text = headline(synthetic_result(frames=4))
    assert "`isik` on PSNR (ahead of `oidn`, untested: 4 paired frames)" in text
    result = synthetic_result()
    entry = result["groups"]["test"]["spp"]["4"]
    for name in ("isik", "oidn"):                            # both exact on one frame: inf − inf
        entry["methods"][name]["per_frame"][0]["metrics"]["psnr"] = math.inf
    annotate(entry, ["l1", "psnr"], resamples=2000, seed=0)
    assert "on PSNR (ahead of `" in headline(result) and "untested: non-finite values (PSNR inf))" in headline(result)


def test_differences_to_oidn_and_noisy_are_attached_to_every_scored_row():
    entry = synthetic_result()["groups"]["test"]["spp"]["4"]
    isik = entry["methods"]["isik"]
    assert set(isik["vs"]) == {"oidn", "noisy"} and "oidn" not in entry["methods"]["oidn"]["vs"]
    assert isik["vs"]["noisy"]["psnr"]["diff"] == pytest.approx(9, abs=0.2)
    assert significant(isik["vs"]["noisy"]["psnr"])
    assert entry["equal_time"]["isik"]["vs"]["oidn"]["psnr"]["diff"] > 2     # MC rows are compared too
    assert isik["ci"]["psnr"]["lo"] < isik["metrics"]["psnr"] < isik["ci"]["psnr"]["hi"]


def test_uncertainty_rank_and_calibration():
    """A σ that is the true error's scale ranks the error well and lies on the diagonal; a σ that
    is noise ranks nothing."""
    from mcdenoise.evaluate.uncertainty import calibration, pixel_pairs, rank_correlation

    rng = np.random.default_rng(0)
    ref = rng.random((64, 64, 3)).astype(np.float32)
    sigma = np.repeat(np.exp(rng.normal(-3, 1, (64, 64, 1))), 3, axis=2).astype(np.float32)
    out = ref + sigma * rng.standard_normal(ref.shape).astype(np.float32)
    s, e = pixel_pairs(sigma, out, ref)
    assert rank_correlation(s, e) > 0.6
    bins = calibration(s, np.abs(out - ref).reshape(-1, 3)[:, 0], bins=8)   # one channel: e ~ |N(0, σ)|
    for b in bins:
        assert 0.7 < b["rmse"] / b["std"] < 1.3
    s_noise, _ = pixel_pairs(rng.random(sigma.shape), out, ref)
    assert abs(rank_correlation(s_noise, e)) < 0.1
    assert rank_correlation(np.zeros_like(s), e) is None
