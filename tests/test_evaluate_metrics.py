"""Evaluation metrics against values computed by hand (or by a direct, independent formula)."""
import math

import numpy as np
import pytest

from mcdenoise.evaluate.scoring import METRICS, best, check_metrics, score
from mcdenoise.pipeline import metrics
from mcdenoise.pipeline.config import ConfigError
from mcdenoise.pipeline.metrics import inverse_reinhard, reinhard

C1, C2 = 0.01 ** 2, 0.03 ** 2


def hdr_of(tonemapped):
    """HDR radiance whose Reinhard tonemap is ``tonemapped``."""
    return inverse_reinhard(np.asarray(tonemapped, dtype=np.float64))


# ---- SSIM ------------------------------------------------------------------------------------


def test_ssim_of_two_flat_images_is_the_luminance_term():
    # Reinhard 1 → 0.5, 3 → 0.75; no variance anywhere, so SSIM = (2·μx·μy + C1) / (μx² + μy² + C1).
    a, b = np.full((12, 12, 3), 1.0), np.full((12, 12, 3), 3.0)
    expected = (2 * 0.5 * 0.75 + C1) / (0.25 + 0.5625 + C1)
    assert metrics.ssim(a, b) == pytest.approx(expected, rel=1e-12)
    assert metrics.ssim(a, a) == pytest.approx(1.0)


def test_ssim_zero_images_and_identical_images():
    z = np.zeros((16, 16, 3))
    assert metrics.ssim(z, z) == 1.0
    x = np.random.default_rng(0).random((16, 16, 3)) * 4
    assert metrics.ssim(x, x) == pytest.approx(1.0, abs=1e-12)


def _ssim_direct(x, y, size):
    """Window by window with an explicit 2-D Gaussian (σ 1.5), Wang et al.'s formula, 'valid' positions."""
    r = np.arange(size) - (size - 1) / 2
    g = np.exp(-r ** 2 / (2 * 1.5 ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    vals = []
    for c in range(x.shape[2]):
        for i in range(x.shape[0] - size + 1):
            for j in range(x.shape[1] - size + 1):
                px, py = x[i:i + size, j:j + size, c], y[i:i + size, j:j + size, c]
                mx, my = (w * px).sum(), (w * py).sum()
                vx, vy = (w * (px - mx) ** 2).sum(), (w * (py - my) ** 2).sum()
                cxy = (w * (px - mx) * (py - my)).sum()
                vals.append((2 * mx * my + C1) * (2 * cxy + C2) / ((mx ** 2 + my ** 2 + C1) * (vx + vy + C2)))
    return float(np.mean(vals))


@pytest.mark.parametrize("shape,window", [((13, 15, 3), 11), ((5, 7, 3), 5), ((8, 8, 1), 7)])
def test_ssim_equals_the_direct_formula(shape, window):
    rng = np.random.default_rng(1)
    tx = rng.random(shape) * 0.9
    ty = np.clip(tx + 0.1 * rng.standard_normal(shape), 0, 0.95)
    got = metrics.ssim(hdr_of(tx), hdr_of(ty))
    assert got == pytest.approx(_ssim_direct(tx, ty, window), rel=1e-9)
    assert got < 1


def test_ssim_hand_value_two_pixels_of_structure():
    # 1×2 image, window shrinks to 1×1: each pixel compares values only, no structure term
    # (σ = 0): pixels (0.5 vs 0.5) and (0.5 vs 0.75) give 1 and the luminance term above.
    a = hdr_of(np.array([[[0.5], [0.5]]]))
    b = hdr_of(np.array([[[0.5], [0.75]]]))
    expected = (1 + (2 * 0.5 * 0.75 + C1) / (0.25 + 0.5625 + C1)) / 2
    assert metrics.ssim(a, b) == pytest.approx(expected, rel=1e-9)


# ---- FLIP ------------------------------------------------------------------------------------

_M = np.array([[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750],
               [0.0193339, 0.1191920, 0.9503041]])


def _hunt_lab(srgb):
    c = np.asarray(srgb, float)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    xyz, white = _M @ lin, _M @ np.ones(3)
    d = 6 / 29

    def f(t):
        return t ** (1 / 3) if t > d ** 3 else t / (3 * d * d) + 4 / 29

    L = 116 * f(xyz[1] / white[1]) - 16
    a = 500 * (f(xyz[0] / white[0]) - f(xyz[1] / white[1]))
    b = 200 * (f(xyz[1] / white[1]) - f(xyz[2] / white[2]))
    return np.array([L, 0.01 * L * a, 0.01 * L * b])          # Hunt-adjusted


def _flip_of_flat_images(s1, s2):
    """FLIP's colour pipeline by hand for two flat sRGB images (no edges: feature error 0)."""
    def hyab(p, q):
        return abs(p[0] - q[0]) + math.hypot(p[1] - q[1], p[2] - q[2])
    cmax = hyab(_hunt_lab([0, 1, 0]), _hunt_lab([0, 0, 1])) ** 0.7
    e = hyab(_hunt_lab(s1), _hunt_lab(s2)) ** 0.7
    pc, pt = 0.4, 0.95
    return e * pt / (pc * cmax) if e < pc * cmax else pt + (e - pc * cmax) / (cmax - pc * cmax) * (1 - pt)


@pytest.mark.parametrize("ref,pred", [([0, 0, 0], [1, 1, 1]), ([0, 0, 0], [3, 3, 3]), ([0.2, 0.5, 1.0], [1.0, 0.3, 0.1])])
def test_ldr_flip_of_flat_images_matches_the_hand_computed_colour_error(ref, pred):
    r, p = np.full((16, 16, 3), ref, float), np.full((16, 16, 3), pred, float)
    expected = _flip_of_flat_images(reinhard(np.array(ref, float)), reinhard(np.array(pred, float)))
    assert metrics.flip(p, r) == pytest.approx(expected, abs=2e-4)


def test_flip_identical_and_black_images():
    x = np.random.default_rng(2).random((16, 16, 3)) * 3
    assert metrics.flip(x, x) == 0.0
    assert metrics.flip(x, x, hdr=True) == 0.0
    z = np.zeros((16, 16, 3))
    # FLIP's own exposure range is log2(x / 0) for a black reference and its C++ core exits the
    # process; the wrapper uses a single exposure there.
    assert metrics.flip(z, z, hdr=True) == 0.0
    assert 0.5 < metrics.flip(z + 1.0, z, hdr=True) <= 1.0
    noisy = np.clip(x + 0.3 * np.random.default_rng(3).standard_normal(x.shape), 0, None)
    assert 0 < metrics.flip(noisy, x, hdr=True)


# ---- FovVideoVDP -----------------------------------------------------------------------------


def test_fvvdp_identical_is_10_jod_and_noise_costs_quality():
    rng = np.random.default_rng(4)
    x = rng.random((32, 32, 3)) * 2
    assert metrics.fvvdp(x, x) == pytest.approx(10.0, abs=1e-4)
    little = np.clip(x + 0.02 * rng.standard_normal(x.shape), 0, None)
    much = np.clip(x + 0.5 * rng.standard_normal(x.shape), 0, None)
    q_little, q_much = metrics.fvvdp(little, x), metrics.fvvdp(much, x)
    assert 10.0 > q_little > q_much


# ---- the metric columns ----------------------------------------------------------------------


def test_score_on_identical_and_zero_images():
    z = np.zeros((16, 16, 3), np.float32)
    s = score(z, z, list(METRICS))
    assert s == {"l1": 0.0, "psnr": math.inf, "ssim": 1.0, "flip": 0.0, "hdr_flip": 0.0,
                 "fvvdp": pytest.approx(10.0, abs=1e-4)}


def test_l1_column_clamps_to_0_6_and_best_follows_direction():
    pred = np.array([[[0.0, 2.0, 10.0]]])
    ref = np.array([[[1.0, 2.0, 4.0]]])
    assert score(pred, ref, ["l1"])["l1"] == pytest.approx((1 + 0 + 2) / 3)
    assert best({"a": 0.1, "b": 0.05, "c": None}, "l1") == {"b"}
    assert best({"a": 30.0, "b": math.inf, "c": float("nan")}, "psnr") == {"b"}
    assert best({"a": 0.9, "b": 0.9}, "ssim") == {"a", "b"}
    with pytest.raises(ConfigError, match="unknown metric 'lpips'"):
        check_metrics(["l1", "lpips"])
