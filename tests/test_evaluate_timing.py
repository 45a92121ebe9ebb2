"""Render-time model, equal-time sample counts and the spp a method is worth, on synthetic numbers."""
import math

import pytest

from mcdenoise.evaluate.report import reference_warning
from mcdenoise.evaluate.timing import RenderCost, equal_time_spp, psnr_to_mse, render_cost, spp_equivalent


def record(stacks, gts, stack_spp=4, gt_spp=1024):
    images = {f"s{k:02d}": {"spp": stack_spp, "render_seconds": t} for k, t in enumerate(stacks)}
    images.update({name: {"spp": gt_spp, "render_seconds": t} for name, t in zip(("gt1", "gt2"), gts)})
    return {"images": images}


def test_render_cost_fits_fixed_and_per_sample_seconds():
    # t(N) = 0.05 + 0.002·N: stacks 0.058 s (one outlier), GT1 includes 1 s of JIT compile.
    cost = render_cost(record([0.058, 0.058, 0.3, 0.058], [0.05 + 2.048 + 1.0, 0.05 + 2.048]))
    assert cost.how == "fit"
    assert cost.b == pytest.approx(0.002)
    assert cost.a == pytest.approx(0.05)
    assert cost.seconds(64) == pytest.approx(0.05 + 0.128)


def test_render_cost_with_progressive_gts_of_different_spp():
    # t(N) = 0.05 + 0.002·N; GT1 stopped at 1024 spp, GT2 at 512 (dataset.gt_target_psnr): the fit pairs
    # the faster GT's time with its own spp.
    rec = record([0.058] * 4, [])
    rec["images"].update({"gt1": {"spp": 1024, "render_seconds": 0.05 + 2.048},
                          "gt2": {"spp": 512, "render_seconds": 0.05 + 1.024}})
    cost = render_cost(rec)
    assert (cost.how, cost.b, cost.a) == ("fit", pytest.approx(0.002), pytest.approx(0.05))


def test_render_cost_without_a_second_sample_count_is_proportional():
    cost = render_cost(record([0.04, 0.04], []))
    assert cost.how == "proportional" and cost.a == 0 and cost.b == pytest.approx(0.01)
    # GT faster than a stack (timer noise): no negative slope, proportional to the GT instead
    cost = render_cost(record([0.5], [0.2]))
    assert cost.how == "proportional" and cost.b == pytest.approx(0.2 / 1024)
    with pytest.raises(ValueError):
        render_cost({"images": {"s00": {"spp": 4}}})


def test_equal_time_spp_adds_what_the_denoise_time_buys():
    cost = RenderCost(a=0.05, b=0.002, how="fit")
    # 4 spp + 0.1 s of denoising: 0.1 / 0.002 = 50 more samples per pixel.
    assert equal_time_spp(4, 0.1, cost) == pytest.approx(54)
    # the equal-time render really takes the same time as render(4) + denoise
    assert cost.seconds(equal_time_spp(4, 0.1, cost)) == pytest.approx(cost.seconds(4) + 0.1)
    assert equal_time_spp(16, 0.0, cost) == 16
    assert equal_time_spp(16, -1.0, cost) == 16        # a clock that went backwards buys nothing


def test_spp_equivalent_interpolates_log_log():
    spp = [4, 8, 16, 64]
    err = [1 / math.sqrt(n) for n in spp]              # MC: error ∝ N^-1/2
    value, how = spp_equivalent(spp, err, 1 / math.sqrt(32))
    assert how == "interpolated" and value == pytest.approx(32)
    assert spp_equivalent(spp, err, 0.5) == (pytest.approx(4), "interpolated")
    value, how = spp_equivalent(spp, err, 1 / math.sqrt(1024))
    assert how == "extrapolated beyond 64 spp" and value == pytest.approx(1024)
    value, how = spp_equivalent(spp, err, 1.0)
    assert how == "extrapolated below 4 spp" and value == pytest.approx(1)


def test_spp_equivalent_does_not_extrapolate_far():
    # a nearly flat last segment would put a good method at an absurd sample count
    assert spp_equivalent([4, 16, 64], [0.1, 0.07, 0.069], 0.006) == (None, "more than 1024 spp (16x past the MC curve)")
    assert spp_equivalent([4, 8], [0.1, 0.099], 0.5) == (None, "less than 0.25 spp (16x below the MC curve)")
    assert spp_equivalent([4, 16], [0.1, 0.05], 0.0125)[0] == pytest.approx(256)        # 16x: still a number


def test_spp_equivalent_honest_failures():
    assert spp_equivalent([4, 8], [0.1, 0.1], 0.01)[0] is None       # flat curve: never reached
    assert spp_equivalent([4, 8], [0.1, 0.05], 0.0) == (None, "unreachable: zero error")
    assert spp_equivalent([4], [0.1], 0.05)[0] is None
    assert spp_equivalent([4, 8], [0.1, 0.05], math.nan)[0] is None
    # PSNR is matched through its MSE: 30 dB ↔ 1e-3; inf dB ↔ 0
    assert psnr_to_mse(30.0) == pytest.approx(1e-3) and psnr_to_mse(math.inf) == 0.0
    mse = [psnr_to_mse(p) for p in (20.0, 23.0103, 26.0206)]     # +3.0103 dB per doubling
    assert spp_equivalent([4, 8, 16], mse, psnr_to_mse(29.0309))[0] == pytest.approx(32, rel=1e-4)


def test_reference_warning_when_mc_stops_converging():
    good = [{"spp": 4, "psnr": 20.0}, {"spp": 16, "psnr": 26.0}, {"spp": 64, "psnr": 32.0}]
    assert reference_warning(good) == []
    flat = [{"spp": 4, "psnr": 20.0}, {"spp": 16, "psnr": 23.0}, {"spp": 64, "psnr": 23.5}]
    text = reference_warning(flat)[0]
    assert "gains only 0.25 dB per doubling of samples between 16 and 64 spp" in text
