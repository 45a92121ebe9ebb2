"""The affinity network: shapes, numerical safety of the kernels, SMAPE at the extremes."""
import numpy as np
import pytest
import torch

from mcdenoise.clean.data import (
    COLOR_VARIANCE_CHANNEL,
    IN_CHANNELS,
    decode_variance,
    frame_inputs,
    relative_variance_feature,
)
from mcdenoise.clean.losses import smape
from mcdenoise.clean.model import AffinityDenoiser, apply_affinity_kernel, range_distance
from mcdenoise.pipeline import schema

# Every model test runs with and without the range term.
RANGE = [None, COLOR_VARIANCE_CHANNEL]


@pytest.fixture(params=RANGE, ids=["affinity_only", "range_term"])
def variance_channel(request):
    return request.param


def small_model(variance_channel=None, **kw):
    torch.manual_seed(0)
    args = dict(embed_channels=8, channels=[8, 12, 16], affinity_channels=4, kernel_size=7, dilations=[1, 2, 4])
    return AffinityDenoiser(IN_CHANNELS, variance_channel=variance_channel, **{**args, **kw}).eval()


@pytest.mark.parametrize("shape", [(13, 21), (1, 1), (5, 64), (32, 32)])
def test_any_size_keeps_shape(shape, variance_channel):
    model = small_model(variance_channel)
    x = torch.randn(2, IN_CHANNELS, *shape)
    r = torch.rand(2, 3, *shape)
    with torch.no_grad():
        y = model(x, r)
    assert y.shape == r.shape and torch.isfinite(y).all()


@pytest.mark.parametrize("value", [0.0, 1e5, 1e30, -1e30])
def test_output_finite_for_extreme_inputs(value, variance_channel):
    model = small_model(variance_channel)
    x = torch.full((1, IN_CHANNELS, 9, 11), value)
    r = torch.full((1, 3, 9, 11), abs(value))
    with torch.no_grad():
        y = model(x, r)
    assert torch.isfinite(y).all()
    # A constant image stays that constant: the weights are normalized.
    torch.testing.assert_close(y, r, rtol=1e-5, atol=0)


def test_output_finite_for_random_hdr_inputs(variance_channel):
    model = small_model(variance_channel)
    g = torch.Generator().manual_seed(1)
    x = torch.randn(1, IN_CHANNELS, 17, 19, generator=g) * 10 ** torch.randint(-3, 6, (1, IN_CHANNELS, 17, 19),
                                                                              generator=g)
    r = torch.rand(1, 3, 17, 19, generator=g) * 1e5
    y = model(x, r)
    assert torch.isfinite(y).all()
    # Convex combination of the input radiance: never outside its range.
    assert y.min() >= r.min() * (1 - 1e-5) and y.max() <= r.max() * (1 + 1e-5)
    y.mean().backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_underflowing_affinities_give_the_centre_pixel():
    g = torch.Generator().manual_seed(2)
    r = torch.rand(1, 3, 10, 12, generator=g) * 100
    f = torch.randn(1, 4, 10, 12, generator=g) * 1e6           # huge feature distances
    bw = torch.full((1, 1, 10, 12), 1e30)                      # huge bandwidth: exp(−inf) = 0
    log_c = torch.full((1, 1, 10, 12), -50.0)                  # tiny centre weight e^-50
    out = apply_affinity_kernel(r, f, bw, log_c, dilation=2, size=7)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, r, rtol=0, atol=0)
    bw_inf = torch.full((1, 1, 10, 12), float("inf"))          # even an infinite bandwidth
    f_same = torch.zeros(1, 4, 10, 12)                          # with zero distances (inf·0)
    out = apply_affinity_kernel(r, f_same, bw_inf, log_c, dilation=1, size=3)
    assert torch.isfinite(out).all()


def test_zero_bandwidth_is_a_box_filter_inside():
    r = torch.arange(5 * 5, dtype=torch.float32).reshape(1, 1, 5, 5)
    out = apply_affinity_kernel(r, torch.zeros(1, 2, 5, 5), torch.zeros(1, 1, 5, 5), torch.zeros(1, 1, 5, 5),
                                dilation=1, size=3)
    # Interior pixel: the mean of its 3×3 neighbourhood; corner: the mean of the 4 pixels inside.
    assert out[0, 0, 2, 2].item() == pytest.approx(r[0, 0, 1:4, 1:4].mean().item())
    assert out[0, 0, 0, 0].item() == pytest.approx(r[0, 0, 0:2, 0:2].mean().item())


def test_smape_finite_at_extremes():
    zero = torch.zeros(1, 3, 4, 4, requires_grad=True)
    loss = smape(zero, torch.zeros(1, 3, 4, 4), 1e-2)
    loss.backward()
    assert loss.item() == 0.0 and torch.isfinite(zero.grad).all()
    big = torch.full((1, 3, 4, 4), 1e5, requires_grad=True)
    loss = smape(big, torch.zeros(1, 3, 4, 4), 1e-2)
    loss.backward()
    assert np.isfinite(loss.item()) and loss.item() == pytest.approx(1.0, abs=1e-6)
    assert torch.isfinite(big.grad).all()
    assert smape(np.full(3, 1e5), np.full(3, 1e5)) == 0.0


@pytest.mark.slow
def test_tiled_inference_matches_whole_frame(variance_channel):
    from mcdenoise.clean.apply import denoise
    model = small_model(variance_channel)
    g = torch.Generator().manual_seed(3)
    x = torch.randn(IN_CHANNELS, 20, 23, generator=g).numpy()
    r = (torch.rand(3, 20, 23, generator=g) * 10).numpy()
    whole = denoise(model, x, r, tile=512)
    # Tiles of 8 with a 32-pixel margin see the whole 20×23 frame: the same result exactly.
    tiled = denoise(model, x, r, tile=8)
    assert whole.shape == (20, 23, 3)
    np.testing.assert_allclose(tiled, whole, rtol=1e-6, atol=1e-6)


def test_variance_feature_resolves_ground_truth_noise_levels():
    """The noise-level input must separate 1024-spp levels (rel ~1e-5..1e-2) as well as 4-spp ones."""
    from mcdenoise.clean.data import relative_variance_feature

    m2 = np.full(5, 0.09, np.float32)                        # radiance 0.3
    rel = np.array([0.0, 1e-5, 1e-3, 1e-1, 1.0], np.float32)
    f = relative_variance_feature(rel * (m2 + 1e-2), m2)
    assert f[0] == pytest.approx(0.0, abs=1e-6)               # noise-free
    assert f[-1] == pytest.approx(1.0, abs=1e-3)              # relative variance 1
    assert np.all(np.diff(f) > 0.15)                          # each decade step is visible
    assert f[2] == pytest.approx(0.5, abs=1e-3)


def test_decode_variance_inverts_the_feature():
    """Round trip: variance → relative-variance feature → variance, over 12 decades of radiance."""
    g = np.random.default_rng(4)
    radiance = (10.0 ** g.uniform(-4, 5, (1, 3, 6, 7))).astype(np.float32)
    mean_square = (radiance ** 2).mean(1)
    rel = 10.0 ** g.uniform(-5.5, 2, mean_square.shape)         # above the 1e-6 floor
    variance = (rel * (mean_square + 1e-2)).astype(np.float32)
    feature = relative_variance_feature(variance, mean_square)
    back = decode_variance(torch.from_numpy(feature)[:, None], torch.from_numpy(radiance))[:, 0].numpy()
    np.testing.assert_allclose(back, variance, rtol=2e-4)
    # Below the floor the decoded variance errs high by at most floor·(m² + 1e-2): it filters less.
    tiny = relative_variance_feature(np.zeros_like(variance), mean_square)
    back0 = decode_variance(torch.from_numpy(tiny)[:, None], torch.from_numpy(radiance))[:, 0].numpy()
    assert np.all(back0 >= 0) and np.all(back0 <= 1.01e-6 * (mean_square + 1e-2))
    # Garbage features decode to finite values.
    junk = torch.tensor([[[[float("inf"), -1e30, 1e30, 0.5]]]])
    assert torch.isfinite(decode_variance(junk, torch.ones(1, 3, 1, 4))).all()


def test_range_distance_matches_the_formula():
    """d² = ((r_p − r_q)² − (v_p + min(v_p, v_q))) / (v_p + v_q), by hand, per pixel (no patch)."""
    r = torch.tensor([[[[0.0, 3.0, 3.0]]]]).expand(1, 3, 1, 3).contiguous()
    v = torch.tensor([[[[1.0, 1.0, 4.0]]]])
    d2 = range_distance(r, v, 0, 1, patch=0)
    # p=0 → q=1: (9 − 2) / 2; p=1 → q=2: (0 − 2) / 5 → clamped to 0; p=2 → q=2 (border): (0 − 8)/8 → 0.
    torch.testing.assert_close(d2[0, 0, 0], torch.tensor([3.5, 0.0, 0.0]))
    # The noise cancels: two noisy copies of one flat image are at distance ≈ 0 on average,
    # a 10σ step is far.
    g = torch.Generator().manual_seed(5)
    flat = 1.0 + 0.01 * torch.randn(1, 3, 64, 64, generator=g)
    var = torch.full((1, 1, 64, 64), 1e-4)
    assert range_distance(flat, var, 0, 1, patch=1).mean() < 0.3
    step = flat.clone()
    step[..., 32:] += 0.1
    assert range_distance(step, var, 0, 1, patch=0)[..., 31].min() > 20
    assert torch.isfinite(range_distance(torch.full((1, 3, 2, 2), 3e38), torch.zeros(1, 1, 2, 2), 1, 0)).all()


def _noisy_frame(truth: np.ndarray, sigma: float, seed: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """Inputs and radiance of a frame whose colour is truth + N(0, σ²), with that variance stored."""
    g = np.random.default_rng(seed)
    buffers = {}
    for b in schema.BUFFERS:
        buffers[b.name] = np.zeros(truth.shape[:2] + (b.size,), np.float32)
        buffers[schema.variance_name(b.name)] = np.zeros(truth.shape[:2] + (b.size,), np.float32)
    buffers["normal"][..., 2] = 1.0
    buffers["albedo"][:] = 0.5
    buffers["color"] = (truth + sigma * g.standard_normal(truth.shape)).astype(np.float32)
    buffers["color.variance"][:] = sigma ** 2
    inputs, radiance = frame_inputs(buffers)
    return inputs, radiance, buffers


def test_untrained_range_term_removes_noise_and_keeps_edges():
    """With the range term an untrained network already behaves as a variance-aware NL-means:
    noise on flat regions drops, a 20σ step edge is not blurred across. Without it, the same
    untrained network does neither."""
    from mcdenoise.clean.apply import denoise

    truth = np.full((48, 48, 3), 0.5, np.float32)
    truth[:, 24:] = 0.7                                          # step of 20σ
    sigma = 0.01
    inputs, radiance, _ = _noisy_frame(truth, sigma, 6)
    noisy_mse = float(np.mean((np.moveaxis(radiance, 0, 2) - truth) ** 2))
    out = denoise(small_model(COLOR_VARIANCE_CHANNEL), inputs, radiance)
    assert np.mean((out - truth) ** 2) < 0.35 * noisy_mse
    # The columns next to the edge keep their side's level (a blur across would move them by 0.1).
    assert np.abs(out[:, 22:24].mean() - 0.5) < 3e-3 and np.abs(out[:, 24:26].mean() - 0.7) < 3e-3
    plain = denoise(small_model(None), inputs, radiance)
    assert np.abs(plain[:, 22:26] - truth[:, 22:26]).mean() > np.abs(out[:, 22:26] - truth[:, 22:26]).mean()
