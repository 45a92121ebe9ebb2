"""The temporal filter and the instability metric (``pipeline.temporal``)."""
import numpy as np
import pytest

from mcdenoise.pipeline.metrics import reinhard
from mcdenoise.pipeline.temporal import blend_history, instability, neighbourhood_range


def test_neighbourhood_range_is_the_3x3_min_and_max():
    img = np.random.default_rng(0).uniform(size=(7, 9, 3)).astype(np.float32)
    lo, hi = neighbourhood_range(img)
    for y in range(7):
        for x in range(9):
            win = img[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2].reshape(-1, 3)
            assert np.array_equal(lo[y, x], win.min(0)) and np.array_equal(hi[y, x], win.max(0))


def test_first_frame_and_invalid_pixels_keep_the_current_output():
    rng = np.random.default_rng(1)
    cur = rng.uniform(size=(8, 8, 3)).astype(np.float32)
    assert np.array_equal(blend_history(cur, None, None, 0.3), cur)
    hist = rng.uniform(size=(8, 8, 3)).astype(np.float32)
    valid = np.zeros((8, 8), bool)
    assert np.array_equal(blend_history(cur, hist, valid, 0.3), cur)
    valid[2:5, 3:6] = True
    out = blend_history(cur, hist, valid, 0.3, clamp=False)
    assert np.array_equal(out[~valid], cur[~valid])
    # float32 arithmetic of one multiply-add: within a few ulps of values below 1
    np.testing.assert_allclose(out[valid], 0.3 * cur[valid] + 0.7 * hist[valid], rtol=0, atol=1e-6)
    assert np.array_equal(blend_history(cur, hist, np.ones((8, 8), bool), 1.0), cur)


def test_the_clamp_bounds_a_wrong_history_by_the_current_neighbourhood():
    cur = np.full((6, 6, 3), 0.5, np.float32)
    cur[3, 3] = 2.0
    hist = np.full((6, 6, 3), 1e6, np.float32)                      # a history that is wrong everywhere
    out = blend_history(cur, hist, np.ones((6, 6), bool), 0.5)
    lo, hi = neighbourhood_range(cur)
    assert np.all(out <= hi) and np.all(out >= lo)
    assert out[0, 0, 0] == 0.5 and out[2, 2, 0] == pytest.approx(0.5 * 0.5 + 0.5 * 2.0)


@pytest.mark.parametrize("weight", [0.0, -0.1, 1.5])
def test_a_weight_outside_0_1_is_refused(weight):
    with pytest.raises(ValueError, match="blend weight"):
        blend_history(np.zeros((2, 2, 3)), None, None, weight)


def test_the_unclamped_filter_on_a_still_frame_keeps_w_over_2_minus_w_of_the_noise_variance():
    """An exponential average with weight w of i.i.d. noise has, in steady state, variance
    w / (2 − w) of one frame's: 1/3 at w = 0.5."""
    rng = np.random.default_rng(2)
    truth, w = np.full((256, 256, 3), 1.0, np.float32), 0.5
    hist = None
    for _ in range(40):                                  # (1 − w)^80: the start is forgotten
        frame = truth + rng.normal(0, 0.1, truth.shape).astype(np.float32)
        hist = blend_history(frame, hist, np.ones(truth.shape[:2], bool), w, clamp=False)
    ratio = float(np.var(hist - truth)) / 0.01
    # 196,608 samples: the variance estimate's relative standard error is sqrt(2/N) = 0.3 %
    assert ratio == pytest.approx(w / (2 - w), rel=0.03)


def test_instability_is_zero_for_the_reference_and_for_an_error_that_stays():
    rng = np.random.default_rng(3)
    ref = rng.uniform(0, 4, (16, 16, 3))
    ref_prev = ref * rng.uniform(0.9, 1.1, ref.shape)                 # the scene changes a little
    valid = np.ones((16, 16), bool)
    assert instability(ref, ref_prev, ref, ref_prev, valid) == 0.0
    biased = ref + 0.3                                                # a still frame with a fixed error
    assert instability(biased, biased, ref, ref, valid) == 0.0


def test_instability_of_fresh_noise_and_the_mask():
    rng = np.random.default_rng(4)
    ref = rng.uniform(0, 1, (32, 32, 3))
    a, b = ref + rng.normal(0, 0.05, ref.shape), ref + rng.normal(0, 0.05, ref.shape)
    valid = rng.uniform(size=(32, 32)) < 0.7
    expected = np.abs(reinhard(a) - reinhard(b))[valid].mean()
    assert instability(a, b, ref, ref, valid) == pytest.approx(expected, rel=1e-12)
    a_bad = a.copy()
    a_bad[~valid] = 1e9                                               # invalid pixels do not count
    assert instability(a_bad, b, ref, ref, valid) == pytest.approx(expected, rel=1e-12)
    assert np.isnan(instability(a, b, ref, ref, np.zeros((32, 32), bool)))
