"""The refine formulation (train/formulation.py) and its sampler: parametrisations, weights, oracle and
zero networks through every sampler and start option, the denoiser's black and over-range rules."""
import re

import numpy as np
import pytest
import torch

from mcdenoise.pipeline.config import ConfigError, load_config
from mcdenoise.train.formulation import Formulation, FormulationError, snr_weight
from mcdenoise.train.sampler import sample, sample_many

G = torch.Generator().manual_seed(0)
X = torch.rand(1, 3, 16, 16, generator=G) * 1.6 - 0.8          # the clean image, model space
EST = (X + 0.05 * torch.randn(X.shape, generator=G)).clamp(-1, 1)  # a first estimate near it
NOISY = (X + 0.3 * torch.randn(X.shape, generator=G)).clamp(-1, 1)


def form(**kw):
    base = dict(prediction="v", schedule="zero_snr", estimate="oidn", residual=True, residual_scale=0.1)
    return Formulation(**{**base, **kw})


class Oracle(torch.nn.Module):
    """Knows the clean image: returns the exact ε, v or x0 target for (z, t) under ``f``."""
    multiple = 1

    def __init__(self, f: Formulation):
        super().__init__()
        self.f, self.acp = f, f.scheduler("ddpm").alphas_cumprod

    def forward(self, z, image, aux, t):
        y = self.f.target(X, image)
        a = self.acp[t].view(-1, 1, 1, 1)
        alpha, sigma = a.sqrt(), (1 - a).sqrt()
        eps = (z - alpha * y) / sigma
        out = {"epsilon": eps, "v": alpha * eps - sigma * y, "sample": y}[self.f.prediction]
        return torch.cat([out, torch.zeros_like(out)], 1)


class Zero(torch.nn.Module):
    """An untrained network whose last layer is zero."""
    multiple = 1

    def forward(self, z, image, aux, t):
        return torch.zeros(z.shape[0], 6, *z.shape[2:])


def test_v_prediction_round_trip():
    """diffusers' get_velocity and x̂0 = α z − σ v̂, ε̂ = σ z + α v̂ recover x and ε at every t."""
    f = form()
    sched = f.scheduler("ddpm")
    eps = torch.randn(X.shape, generator=torch.Generator().manual_seed(1))
    for t in (0, 250, 700, 998):
        tt = torch.tensor([t])
        z = sched.add_noise(X, eps, tt)
        v = sched.get_velocity(X, eps, tt)
        a = sched.alphas_cumprod[t]
        torch.testing.assert_close(a.sqrt() * z - (1 - a).sqrt() * v, X, atol=1e-5, rtol=0)
        torch.testing.assert_close((1 - a).sqrt() * z + a.sqrt() * v, eps, atol=1e-5, rtol=0)


@pytest.mark.parametrize("prediction", ["v", "sample"])
@pytest.mark.parametrize("sampler", ["ddim", "ddpm"])
@pytest.mark.parametrize("start,steps,skip", [("noise", 1, 0), ("noise", 9, 0), ("estimate", 9, 3),
                                              ("render", 27, 12), ("estimate", 3, 0)])
def test_oracle_network_recovers_the_image(prediction, sampler, start, steps, skip):
    f = form(prediction=prediction)
    out = sample(Oracle(f), NOISY, None, image=EST, formulation=f, steps=steps, skip=skip, start=start,
                 sampler=sampler, seed=3)
    torch.testing.assert_close(out, X, atol=2e-5, rtol=0)


@pytest.mark.parametrize("schedule,prediction", [("if", "v"), ("if", "sample")])
def test_oracle_without_residual_or_zero_snr(schedule, prediction):
    f = form(schedule=schedule, prediction=prediction, residual=False, estimate="none")
    out = sample(Oracle(f), NOISY, None, formulation=f, steps=9, skip=4, start="render", seed=0)
    torch.testing.assert_close(out, X, atol=2e-5, rtol=0)


def test_one_step_from_t_returns_the_networks_x0():
    """Zero terminal SNR: one DDIM step from T = the network's x̂0 = −v̂ (α_T = 0, σ_T = 1)."""
    f = form(prediction="v")
    v_hat = torch.randn(X.shape, generator=torch.Generator().manual_seed(5)) * 0.3

    class Fixed(torch.nn.Module):
        multiple = 1

        def forward(self, z, image, aux, t):
            assert int(t[0]) == 999
            return torch.cat([v_hat, torch.zeros_like(v_hat)], 1)

    out = sample(Fixed(), NOISY, None, image=EST, formulation=f, steps=1, start="noise", seed=7)
    torch.testing.assert_close(out, (EST + 0.1 * (-v_hat)).clamp(-1, 1), atol=1e-6, rtol=0)


@pytest.mark.parametrize("sampler", ["ddim", "ddpm"])
@pytest.mark.parametrize("start,steps,skip", [("noise", 1, 0), ("estimate", 27, 0), ("render", 9, 4)])
def test_untrained_sample_prediction_returns_the_estimate_exactly(sampler, start, steps, skip):
    f = form(prediction="sample")
    out = sample(Zero(), NOISY, None, image=EST, formulation=f, steps=steps, skip=skip, start=start, sampler=sampler,
                 seed=2)
    if sampler == "ddim":
        assert torch.equal(out, EST)
    else:   # DDPM's last step still draws noise with diffusers' variance floor of 1e-20 (std 1e-10)
        torch.testing.assert_close(out, EST, atol=1e-7, rtol=0)


def test_min_snr_weight_has_a_floor_at_zero_snr_and_gamma_at_low_noise():
    f = form()
    sched = f.scheduler("ddpm")
    t = torch.tensor([0, 500, 999])
    w0 = snr_weight(sched, t, "sample", gamma=5.0, floor=1.0)
    assert w0[2] == pytest.approx(1.0) and w0[0] == pytest.approx(5.0)
    wv = snr_weight(sched, t, "v", gamma=5.0, floor=1.0)
    assert wv[2] == pytest.approx(1.0) and wv[0] < 1e-3      # x0-error weight 5 over SNR + 1 ≫ 1
    assert torch.all(snr_weight(sched, t, "sample", 5.0, 0.0)[:2] > 0)
    assert snr_weight(sched, t, "sample", 5.0, 0.0)[2] == 0      # the trap the floor avoids


def test_training_timesteps_focus_on_the_samplers_steps():
    f = form(t_focus=1.0)
    focus = f.train_timesteps([1, 3])
    assert [x.tolist() for x in focus] == [[999], [999, 666, 332]]
    t = f.draw_t(6000, focus, torch.Generator().manual_seed(0)).numpy()
    assert set(t.tolist()) <= {332, 666, 999}
    # each step count half the time: 999 in 1/2 + 1/6 of the draws, 666 and 332 in 1/6 each
    assert abs((t == 999).mean() - 2 / 3) < 0.03 and abs((t == 332).mean() - 1 / 6) < 0.03
    mixed = form(t_focus=0.5).draw_t(4000, focus, torch.Generator().manual_seed(0))
    share = np.isin(mixed.numpy(), [332, 666, 999]).mean()
    assert 0.45 < share < 0.56


def test_loss_is_zero_for_the_oracle_and_positive_otherwise():
    for prediction in ("v", "sample"):
        f = form(prediction=prediction)
        sched = f.scheduler("ddpm")
        y = f.target(X, EST)
        t = torch.tensor([999])
        noise = torch.randn(X.shape, generator=torch.Generator().manual_seed(4))
        z = sched.add_noise(y, noise, t)
        exact = Oracle(f)(z, EST, None, t)
        assert float(f.loss(exact, y, z, t, noise, sched)[0]) < 1e-10
        assert float(f.loss(torch.zeros_like(exact), y, z, t, noise, sched)[0]) > 1e-3


def _two_crops(f):
    """An easy crop and one whose first estimate is 30 times further off (both far above the floor)."""
    gen = torch.Generator().manual_seed(7)
    image = (torch.rand(2, 3, 16, 16, generator=gen) * 1.6 - 0.8)
    err = 0.03 * torch.randn(image.shape, generator=gen)
    err[1] *= 30
    return f.target(image + err, image), image


@pytest.mark.parametrize("norm", ["none", "crop"])
def test_crop_norm_counts_every_crop_by_its_relative_gain(norm):
    f = form(prediction="sample", loss_norm=norm)
    sched = f.scheduler("ddpm")
    y, image = _two_crops(f)
    t = torch.tensor([999, 999])
    z = torch.randn(y.shape, generator=torch.Generator().manual_seed(1))
    weights = f.crop_norm(y, image)

    def loss_of(pred):
        return float(f.loss(torch.cat([pred, torch.zeros_like(pred)], 1), y, z, t, z, sched, norm=weights)[0])
    fix_easy = torch.stack([y[0] / 2, torch.zeros_like(y[1])])   # halves the easy crop's error only
    fix_hard = torch.stack([torch.zeros_like(y[0]), y[1] / 2])   # halves the hard crop's error only
    start = loss_of(torch.zeros_like(y))                           # the estimate itself
    gain_easy, gain_hard = start - loss_of(fix_easy), start - loss_of(fix_hard)
    assert gain_easy > 0 and gain_hard > 0
    if norm == "crop":
        assert gain_easy == pytest.approx(gain_hard, rel=3e-3)
        assert start == pytest.approx(1.0, rel=3e-3)                 # every crop's estimate scores 1
    else:                                                             # 30x the error: 900x the say
        assert weights is None
        assert gain_hard > 500 * gain_easy


def test_crop_norm_is_finite_where_the_estimate_is_exact():
    f = form(prediction="sample", loss_norm="crop")
    y, image = _two_crops(f)
    y[0] = 0                                                      # the estimate is the clean image
    w = f.crop_norm(y, image)
    assert torch.all(torch.isfinite(w)) and torch.all(w > 0)
    sched = f.scheduler("ddpm")
    t = torch.tensor([999, 999])
    off = torch.full_like(y, 0.01)
    loss = f.loss(torch.cat([off, off], 1), y, y, t, y, sched, norm=w)[0]
    assert torch.isfinite(loss)


def test_training_objective_with_crop_norm_starts_at_one_for_an_untrained_network():
    f = form(prediction="sample", loss_norm="crop", t_focus=1.0)
    y, image = _two_crops(f)
    x = f.image_of(y, image)
    net = torch.nn.Conv2d(3, 6, 1)
    torch.nn.init.zeros_(net.weight), torch.nn.init.zeros_(net.bias)
    step = f.objective([1])
    loss, terms = step(lambda z, im, aux, t: net(z), {"target": x, "image": image, "noisy": image, "aux": None},
                       torch.Generator().manual_seed(0), torch.device("cpu"), None)
    assert float(loss.detach()) == pytest.approx(1.0, rel=1e-3)
    loss.backward()
    assert net.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("bad,match", [
    (dict(loss_norm="pixel"), "diffusion.loss_norm"),
    (dict(prediction="epsilon"), "zero terminal SNR"),
    (dict(prediction="epsilon", schedule="if"), "paper formulation"),
    (dict(estimate="none"), "needs a first estimate"),
    (dict(start="middle"), "diffusion.start"),
    (dict(steps=3, skip=3), "diffusion.skip"),
])
def test_formulation_refuses_what_cannot_work(bad, match):
    with pytest.raises(FormulationError, match=match):
        form(**bad)


def test_steps_and_skips_of_each_formulation():
    assert form(steps=50, skip=30).skip == 30                      # refine: skip counts in its own steps
    with pytest.raises(FormulationError, match=r"^diffusion\.skip: need 0 <= skip < steps \(50\), got 50$"):
        form(steps=50, skip=50)
    with pytest.raises(FormulationError, match=r"^diffusion\.steps: need 1 <= steps <= 1000, got 0$"):
        form(steps=0)
    paper = dict(prediction="epsilon", schedule="if", residual=False, estimate="none")
    assert form(**paper, skip=26).skip == 26                        # paper: skip counts in super27
    with pytest.raises(FormulationError, match=r"^diffusion\.skip: the paper formulation skips 0\.\.26"):
        form(**paper, skip=27)


def test_every_configurable_prediction_has_a_diffusers_type():
    from mcdenoise.pipeline.config import PREDICTIONS
    from mcdenoise.train.formulation import PREDICTION_TYPES
    assert set(PREDICTION_TYPES) == set(PREDICTIONS)
    for prediction in PREDICTIONS:   # each one the config accepts builds its scheduler
        f = form(prediction=prediction, schedule="if", residual=False, estimate="none")
        assert f.scheduler("ddim").config.prediction_type == PREDICTION_TYPES[prediction]


def test_a_record_with_a_bad_combination_is_refused():
    """Formulation is also built from model.json records: it checks itself, whatever the source."""
    record = form().record()
    with pytest.raises(FormulationError, match=r"diffusion\.skip"):
        Formulation.from_record({**record, "steps": 3, "skip": 3})
    assert issubclass(FormulationError, ConfigError)


GRID = [dict(prediction=p, schedule=s, residual=r, estimate=e, steps=n, skip=k)
        for p in ("epsilon", "v", "sample") for s in ("if", "zero_snr") for r in (True, False)
        for e in ("none", "oidn") for n, k in ((1, 0), (50, 30), (50, 50), (27, 27))]


@pytest.mark.parametrize("values", GRID, ids=lambda v: "-".join(str(x) for x in v.values()))
def test_the_config_and_the_formulation_apply_the_same_rules(values):
    """One set of rules (pipeline.config.check_formulation): a diffusion section loads exactly when a
    Formulation of the same fields can be built, and both name the same key."""
    def outcome(build):
        try:
            build()
        except ConfigError as exc:
            return re.search(r"diffusion\.\w+", str(exc)).group(0)
        return "ok"
    in_config = outcome(lambda: load_config(None, [f"diffusion.{k}={v}" for k, v in values.items()]))
    assert in_config == outcome(lambda: form(**values))


def test_samples_mean_and_std():
    f = form(prediction="sample")

    class Noisy(torch.nn.Module):
        """x̂0 = the true residual + noise drawn from z: samples differ, their mean is near the truth."""
        multiple = 1

        def forward(self, z, image, aux, t):
            y = f.target(X, image)
            return torch.cat([y + 0.5 * z, torch.zeros_like(z)], 1)

    one_mean, one_std = sample_many(Noisy(), NOISY, None, samples=1, image=EST, formulation=f, steps=1,
                                    start="noise", seed=0)
    assert torch.equal(one_std, torch.zeros_like(one_std))
    mean, std = sample_many(Noisy(), NOISY, None, samples=6, image=EST, formulation=f, steps=1, start="noise", seed=0)
    assert torch.all(std >= 0) and float(std.mean()) > 0.01
    assert float((mean - X).abs().mean()) < float((one_mean - X).abs().mean())


# ---- the denoiser around the model (train/infer.py) ------------------------------------------------

def tiny_denoiser(estimate="oidn"):
    from mcdenoise.train.infer import Denoiser
    from tests.helpers import tiny_model

    f = form(prediction="sample", estimate=estimate, residual=estimate != "none")
    m = tiny_model().eval()
    torch.nn.init.normal_(m.base.conv_out.weight, std=0.5)   # an imperfect network: it changes its input
    return Denoiser(m, {"tonemap": "log", "formulation": f.record()}, torch.device("cpu"))


@pytest.mark.parametrize("estimate", ["oidn", "none"])
def test_black_in_black_out(estimate):
    den = tiny_denoiser(estimate)
    from mcdenoise.evaluate.stability import synthetic_buffers

    buffers = synthetic_buffers(16, 16, seed=2)
    buffers["color"][:] = 0
    out, std = den.denoise(buffers, spp=4, with_std=True)
    assert den.last_black and not out.any() and not std.any()
    buffers["color"][3, 4] = 0.2                                          # one lit pixel: the network runs
    assert den.denoise(buffers, spp=4).any() and not den.last_black and not den.last_estimate_only


def test_radiance_beyond_the_model_range_keeps_the_first_estimate():
    from mcdenoise.evaluate.stability import synthetic_buffers
    from mcdenoise.pipeline import oidn

    den = tiny_denoiser("oidn")
    buffers = synthetic_buffers(16, 16, seed=1)          # the renderer's buffers: the network runs
    buffers["color"][4:8, 4:8] = 1e5
    est = oidn.denoise(buffers)
    out = den.denoise(buffers, spp=4)
    assert not den.last_estimate_only
    over = (est > 6).any(axis=2)
    assert over.any() and den.last_clamped == int(over.sum())
    np.testing.assert_array_equal(out[over], est[over])
    assert out[~over].max() <= 6.0


def test_an_rgb_only_input_returns_the_first_estimate():
    from mcdenoise.pipeline import oidn
    den = tiny_denoiser("oidn")
    color = np.random.default_rng(3).gamma(1.0, 0.3, (16, 16, 3)).astype(np.float32)
    out = den.denoise({"color": color}, spp=16)
    assert den.last_estimate_only
    np.testing.assert_array_equal(out, oidn.denoise({"color": color}))


def test_records_round_trip_and_runs_from_before_loss_norm_keep_their_fingerprint():
    crop = form(loss_norm="crop")
    assert Formulation.from_record(crop.record()) == crop
    # train/shipped/model.json's record as exported before the key existed
    before = {"estimate": "oidn", "prediction": "sample", "residual": True, "residual_scale": 0.05, "sampler": "ddim",
              "schedule": "zero_snr", "skip": 0, "snr_floor": 1.0, "snr_gamma": 5.0, "start": "estimate", "steps": 1,
              "t_focus": 0.8}
    old = Formulation.from_record(before)
    assert old.loss_norm == "none" and old.record() == before
