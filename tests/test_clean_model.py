"""The affinity network: shapes, numerical safety of the kernels, SMAPE at the extremes."""
import numpy as np
import pytest
import torch

from clean.data import IN_CHANNELS
from clean.losses import smape
from clean.model import AffinityDenoiser, apply_affinity_kernel


def small_model(**kw):
    torch.manual_seed(0)
    args = dict(embed_channels=8, channels=[8, 12, 16], affinity_channels=4, kernel_size=7, dilations=[1, 2, 4])
    return AffinityDenoiser(IN_CHANNELS, **{**args, **kw}).eval()


@pytest.mark.parametrize("shape", [(13, 21), (1, 1), (5, 64), (32, 32)])
def test_any_size_keeps_shape(shape):
    model = small_model()
    x = torch.randn(2, IN_CHANNELS, *shape)
    r = torch.rand(2, 3, *shape)
    with torch.no_grad():
        y = model(x, r)
    assert y.shape == r.shape and torch.isfinite(y).all()


@pytest.mark.parametrize("value", [0.0, 1e5, 1e30, -1e30])
def test_output_finite_for_extreme_inputs(value):
    model = small_model()
    x = torch.full((1, IN_CHANNELS, 9, 11), value)
    r = torch.full((1, 3, 9, 11), abs(value))
    with torch.no_grad():
        y = model(x, r)
    assert torch.isfinite(y).all()
    # A constant image stays that constant: the weights are normalized.
    torch.testing.assert_close(y, r, rtol=1e-5, atol=0)


def test_output_finite_for_random_hdr_inputs():
    model = small_model()
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


def test_tiled_inference_matches_whole_frame():
    from clean.apply import denoise
    model = small_model()
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
    from clean.data import relative_variance_feature

    m2 = np.full(5, 0.09, np.float32)                        # radiance 0.3
    rel = np.array([0.0, 1e-5, 1e-3, 1e-1, 1.0], np.float32)
    f = relative_variance_feature(rel * (m2 + 1e-2), m2)
    assert f[0] == pytest.approx(0.0, abs=1e-6)               # noise-free
    assert f[-1] == pytest.approx(1.0, abs=1e-3)              # relative variance 1
    assert np.all(np.diff(f) > 0.15)                          # each decade step is visible
    assert f[2] == pytest.approx(0.5, abs=1e-3)
