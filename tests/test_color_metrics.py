"""Tonemappers (round trips, numpy and torch alike) and metrics against hand-computed values."""
import math

import numpy as np
import pytest
import torch

from mcdenoise.pipeline import metrics
from mcdenoise.pipeline.metrics import (
    gamma_compress,
    inverse_gamma_compress,
    inverse_log_compress,
    inverse_reinhard,
    linear_to_srgb,
    log_compress,
    reinhard,
    srgb_to_linear,
)

PAIRS = [
    (reinhard, inverse_reinhard),
    (log_compress, inverse_log_compress),
    (gamma_compress, inverse_gamma_compress),
]
VALUES = [0.0, 1e-4, 0.5, 1.0, 6.0, 1e5]


@pytest.mark.parametrize("fwd,inv", PAIRS)
def test_round_trip_numpy(fwd, inv):
    x = np.array(VALUES, dtype=np.float64)
    np.testing.assert_allclose(inv(fwd(x)), x, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("fwd,inv", PAIRS)
def test_round_trip_torch_float32(fwd, inv):
    x = torch.tensor(VALUES, dtype=torch.float32)
    y = fwd(x)
    assert isinstance(y, torch.Tensor) and y.dtype == torch.float32
    # float32 Reinhard of 1e5 keeps ~2 digits (1 − 1e−5 next to 1): a loose tolerance there.
    torch.testing.assert_close(inv(y)[:-1], x[:-1], rtol=1e-5, atol=1e-6)
    assert inv(y)[-1].item() == pytest.approx(1e5, rel=1e-2)


def test_srgb_transfer_round_trip_and_known_values():
    x = np.array([0.0, 0.001, 0.0031308, 0.01, 0.18, 0.5, 1.0])
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, rtol=1e-12, atol=1e-15)
    assert linear_to_srgb(0.001) == pytest.approx(0.01292) and linear_to_srgb(1.0) == pytest.approx(1.0)
    assert linear_to_srgb(0.18) == pytest.approx(0.4614, abs=1e-4)
    assert linear_to_srgb(-1.0) == 0.0 and linear_to_srgb(7.0) == pytest.approx(1.0)   # clamped to [0, 1]
    t = linear_to_srgb(torch.tensor([0.0, 0.18, 1.0]))
    assert t.dtype == torch.float32 and t[1].item() == pytest.approx(0.4614, abs=1e-4)


def test_known_values():
    assert reinhard(1.0) == 0.5
    assert reinhard(-3.0) == 0.0                      # negative radiance clamps to 0
    assert log_compress(6.0) == pytest.approx(0.51 * math.log(7.0))
    assert gamma_compress(6.0) == pytest.approx(0.47 * 6.0 ** (1 / 2.4))
    assert 0.98 < log_compress(6.0) < 1.0 and 0.98 < gamma_compress(6.0) < 1.0
    assert np.isfinite(inverse_reinhard(1.0))          # clamped below 1: finite


def test_psnr():
    a = np.zeros((4, 4, 3))
    assert metrics.psnr(a, a) == math.inf
    # Reinhard(1) = 0.5 against 0 on every pixel: MSE 0.25 → 10·log10(4) dB.
    assert metrics.psnr(np.ones((4, 4, 3)), a) == pytest.approx(10 * math.log10(4.0))
    # One of 4 pixels off by reinhard 0.5: MSE 0.0625 → 12.04 dB; torch gives the same.
    b = np.zeros((2, 2, 1))
    b[0, 0, 0] = 1.0
    assert metrics.psnr(b, np.zeros((2, 2, 1))) == pytest.approx(10 * math.log10(16.0))
    assert metrics.psnr(torch.tensor(b), torch.zeros(2, 2, 1, dtype=torch.float64)) == pytest.approx(
        10 * math.log10(16.0))


def test_l1_and_clamp():
    pred = np.array([0.0, 2.0, 10.0, -1.0])
    ref = np.array([1.0, 2.0, 4.0, 0.0])
    assert metrics.l1(pred, ref) == pytest.approx((1 + 0 + 6 + 1) / 4)
    assert metrics.l1(pred, ref, clamp=(0, 6)) == pytest.approx((1 + 0 + 2 + 0) / 4)


def test_smape_hand_values():
    # |1−3|/(1+3+0.01) and 0/(0+0.01): mean of the two.
    a, b = np.array([1.0, 0.0]), np.array([3.0, 0.0])
    assert metrics.smape(a, b, eps=0.01) == pytest.approx((2 / 4.01 + 0) / 2)
    t = metrics.smape(torch.tensor(a), torch.tensor(b), eps=0.01)
    assert isinstance(t, torch.Tensor) and t.item() == pytest.approx((2 / 4.01) / 2)
    assert metrics.smape(np.zeros(5), np.zeros(5)) == 0.0
    assert metrics.smape(np.full(5, 1e5), np.zeros(5)) == pytest.approx(1.0, abs=1e-6)


def test_all_metrics_keys():
    x = np.random.default_rng(0).random((8, 8, 3))
    m = metrics.all_metrics(x, x)
    assert m == {"psnr": math.inf, "l1": 0.0, "smape": 0.0}
