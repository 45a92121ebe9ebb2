"""The diffusion denoiser's pieces on tiny models: transforms, DDPM math, Control Module, sampler, training loop."""
import json

import numpy as np
import pytest
import torch

from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.errors import CheckpointError
from mcdenoise.pipeline.fit import fit
from mcdenoise.train import base as base_lib, diffusion
from mcdenoise.train.control import ControlledDenoiser
from mcdenoise.train.data import AUX_CHANNELS, augment, aux_names, condition, from_model, to_model
from mcdenoise.train.sampler import sample, sample_tiled
from mcdenoise.train.train import ControlTask, TrainError, lr_factor
from tests.helpers import tiny_model, tiny_unet_config

TINY_UNET = tiny_unet_config()

# ---- transforms ---------------------------------------------------------------------------------

@pytest.mark.parametrize("tonemap", ["log", "gamma"])
def test_model_space_round_trip(tonemap):
    x = np.concatenate([np.linspace(0, 6, 1001), [0.0, 1e-6, 5.999]]).astype(np.float32)
    y = to_model(x, tonemap)
    assert y.min() >= -1 and y.max() <= 1
    np.testing.assert_allclose(from_model(y, tonemap), x, rtol=2e-5, atol=2e-6)
    xt = torch.from_numpy(x)
    torch.testing.assert_close(from_model(to_model(xt, tonemap), tonemap), xt, rtol=2e-5, atol=2e-6)
    # Out-of-range radiance is clamped, never NaN: 1e5 -> 6, negative -> 0.
    np.testing.assert_allclose(from_model(to_model(np.array([1e5, -3.0], np.float32), tonemap), tonemap),
                               [6.0, 0.0], rtol=1e-5)


def sphere_normals(n=9):
    """Camera-space normals of a sphere seen head-on: symmetric under every flip and quarter turn."""
    ys, xs = np.mgrid[0:n, 0:n].astype(np.float32)
    x, y = (xs - (n - 1) / 2) / n, -(ys - (n - 1) / 2) / n   # x right, y up
    z = np.sqrt(np.clip(1 - x * x - y * y, 0, 1))
    return np.stack([x, y, z], 2)


def test_augment_turns_normals_with_the_image():
    buffers = {"color": np.random.default_rng(0).random((9, 9, 3), np.float32), "normal": sphere_normals()}
    aux = condition(buffers, 4)
    sl = slice(aux_names().index("normal.X"), aux_names().index("normal.X") + 3)
    for fx, fy, rot in [(True, False, 0), (False, True, 0), (False, False, 1), (True, True, 3), (False, False, 2)]:
        (out,) = augment([aux], fx, fy, rot, aux_index=0)
        np.testing.assert_allclose(out[sl], aux[sl], atol=1e-6, err_msg=f"flip {fx},{fy} rot {rot}")
    # A plain gradient image: its normals must *not* stay put (the test above can fail).
    tilted = np.zeros((9, 9, 3), np.float32)
    tilted[..., 0] = 1.0   # every normal points right
    aux = condition({"color": buffers["color"], "normal": tilted}, 4)
    (out,) = augment([aux], False, False, 1, aux_index=0)
    np.testing.assert_allclose(out[sl][1], 1.0, atol=1e-6)   # right, turned a quarter counter-clockwise: up
    np.testing.assert_allclose(out[sl][0], 0.5, atol=1e-6)


def test_condition_has_every_channel_and_any_missing_buffer_is_background():
    rng = np.random.default_rng(1)
    full = condition({"color": rng.random((5, 7, 3), np.float32) * 10}, 16)
    assert full.shape == (AUX_CHANNELS, 5, 7) and np.all(np.isfinite(full))
    assert full[-1].min() == full[-1].max() == pytest.approx(4 / 6)   # log2(16)/6


# ---- DDPM math ----------------------------------------------------------------------------------

def test_learned_variance_matches_the_sampler():
    sched = diffusion.make_scheduler()
    acp = sched.alphas_cumprod
    v = torch.linspace(-1, 1, 5).view(5, 1, 1, 1)
    for t in [1, 10, 500, 999]:
        ours = diffusion.log_variance(v, torch.full((5,), t), acp).flatten()
        theirs = torch.stack([sched._get_variance(t, predicted_variance=vi.view(1)).flatten()[0] for vi in v])
        torch.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-5)


def test_q_sample_inverse_and_vlb():
    acp = diffusion.make_scheduler().alphas_cumprod
    g = torch.Generator().manual_seed(0)
    x = torch.rand(4, 3, 8, 8, generator=g) * 2 - 1
    eps = torch.randn(x.shape, generator=g)
    t = torch.tensor([0, 1, 500, 999])
    z = diffusion.q_sample(x, t, eps, acp)
    torch.testing.assert_close(diffusion.predict_x0(z, t, eps, acp), x, rtol=1e-3, atol=2e-3)
    # The true ε and the posterior's own variance (v = −1 is β̃_t) give KL 0 for t > 0.
    vb = diffusion.vlb_term(x, z, t, eps, -torch.ones_like(x), acp)
    assert torch.all(vb[1:].abs() < 1e-3), vb
    assert torch.isfinite(vb).all()
    loss, terms = diffusion.loss(torch.cat([eps, torch.zeros_like(x)], 1), x, z, t, eps, acp)
    assert terms["mse"] == 0 and torch.isfinite(loss)


def test_paper_step_count_is_ifs_super27():
    assert len(diffusion.super27()) == diffusion.PAPER_STEPS == 27


def test_lr_schedule():
    assert lr_factor(0, 100, 10) == pytest.approx(0.1)
    assert lr_factor(9, 100, 10) == pytest.approx(1.0)
    assert lr_factor(100, 100, 10) == pytest.approx(0.0, abs=1e-12)
    assert 0.49 < lr_factor(55, 100, 10) < 0.51


# ---- Control Module -----------------------------------------------------------------------------

def inputs(B=2, H=16, W=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, 3, H, W, generator=g), torch.rand(B, 3, H, W, generator=g) * 2 - 1,
            torch.rand(B, AUX_CHANNELS, H, W, generator=g), torch.tensor([3, 900])[:B])


def test_zero_initialised_control_leaves_the_base_unchanged():
    m = tiny_model()
    z, noisy, aux, t = inputs()
    with torch.no_grad():
        a = m(z, noisy, aux, t)
        m.control = None
        b = m(z, noisy, aux, t)
    assert torch.equal(a, b)


def test_control_encoder_reproduces_the_base_encoder():
    """With the stem at zero, the copied encoder's skips are exactly the base's own (same embeddings)."""
    m = tiny_model()
    for zc in list(m.control.zero_convs) + [m.control.zero_mid]:
        torch.nn.init.dirac_(zc.weight)
    z, noisy, aux, t = inputs()
    seen = []
    hooks = [blk.register_forward_hook(lambda mod, i, o: seen.append(o)) for blk in m.base.down_blocks]
    sample_in = torch.cat([z, noisy], 1)
    with torch.no_grad():
        down, _ = m.control(sample_in, t, aux, torch.zeros(2, dtype=torch.long), m.prompt.expand(2, -1, -1))
        m.base(sample_in, t, encoder_hidden_states=m.prompt.expand(2, -1, -1), class_labels=torch.zeros(2)).sample
    for h in hooks:
        h.remove()
    base_skips = [r for _, res in seen for r in res]
    for mine, theirs in zip(down[1:], base_skips, strict=True):
        torch.testing.assert_close(mine, theirs)


class Synthetic(torch.utils.data.Dataset):
    def __init__(self, n=8, side=16, nan_at=None):
        g = torch.Generator().manual_seed(0)
        self.target = torch.rand(n, 3, side, side, generator=g) * 2 - 1
        self.noisy = (self.target + 0.3 * torch.randn(self.target.shape, generator=g)).clamp(-1, 1)
        self.aux = torch.rand(n, AUX_CHANNELS, side, side, generator=g)
        self.nan_at = nan_at

    def set_epoch(self, epoch):
        pass

    def __len__(self):
        return len(self.target)

    def __getitem__(self, i):
        noisy = self.noisy[i].clone()
        if self.nan_at is not None:
            noisy[0, 0, 0] = float("nan")
        return {"noisy": noisy, "aux": self.aux[i], "target": self.target[i]}


# The paper's arrangement on a tiny frozen base: IF's hybrid loss, the noisy render as the image input.
PAPER = ["diffusion.prediction=epsilon", "diffusion.schedule=if", "diffusion.residual=false",
         "diffusion.estimate=none", "diffusion.train_base=false"]


def task(folder, epochs, data=None, *overrides):
    """``train.train.ControlTask`` on a tiny saved base and ``data`` (default ``Synthetic()``) instead of a store."""
    base = folder / "base"
    if not base.exists():
        base_lib.save(base, *base_lib.build(TINY_UNET, seed=0))
    cfg = load_config(None, [f"runs={folder / 'runs'}", f"diffusion.base={base}", *PAPER, f"diffusion.epochs={epochs}",
                             "diffusion.batch_size=4", "diffusion.lr=1e-3", "diffusion.warmup_steps=1",
                             "diffusion.nan_limit=3", "diffusion.ema=0", "diffusion.device=cpu", *overrides])
    return ControlTask(cfg, "any", data=data or Synthetic())


def test_training_moves_only_the_control_module(tmp_path):
    t = task(tmp_path, 2)
    base_before = {k: v.clone() for k, v in t.model.base.state_dict().items()}
    control_before = {k: v.clone() for k, v in t.model.control.state_dict().items()}
    summary = fit(t, quiet=True)
    assert summary["epochs"] == 2
    assert all(torch.equal(base_before[k], v) for k, v in t.model.base.state_dict().items())
    assert any(not torch.equal(control_before[k], v) for k, v in t.model.control.state_dict().items())
    assert (t.folder / "loss.png").stat().st_size > 1000
    hist = json.loads((t.folder / "train.json").read_text())["history"]
    assert len(hist) == 2 and all(np.isfinite(h["train_loss"]) for h in hist)
    assert (t.folder / "control.safetensors").exists() and (t.folder / "model.json").exists()


class Counting(Synthetic):
    def __init__(self):
        super().__init__()
        self.read = []

    def __getitem__(self, i):
        self.read.append(i)
        return super().__getitem__(i)


def test_epoch_steps_trains_a_new_subset_each_epoch(tmp_path):
    ds = Counting()
    t = task(tmp_path, 2, ds, "diffusion.epoch_steps=1")   # 1 step of batch 4 per epoch
    fit(t, quiet=True)
    first, second = ds.read[:4], ds.read[4:]
    assert len(ds.read) == 8 and len(set(first)) == 4 and set(first) != set(second)
    hist = json.loads((t.folder / "train.json").read_text())["history"]
    assert [h["epoch"] for h in hist] == [1, 2]


def test_resume_continues_exactly(tmp_path):
    straight = task(tmp_path / "a", 3)
    fit(straight, quiet=True)
    stopped = task(tmp_path / "b", 3, None, "diffusion.time_budget_s=1e-9")   # stops after its first epoch
    assert fit(stopped, quiet=True)["epochs"] == 1
    again = task(tmp_path / "b", 3)   # a new process: fresh weights, everything must come from last.safetensors
    fit(again, quiet=True)
    for k, v in straight.model.control.state_dict().items():
        assert torch.equal(v, again.model.control.state_dict()[k]), k
    a = json.loads((straight.folder / "train.json").read_text())["history"]
    b = json.loads((again.folder / "train.json").read_text())["history"]
    assert [h["train_loss"] for h in a] == [h["train_loss"] for h in b]


def test_nan_guard_skips_then_stops(tmp_path):
    with pytest.raises(TrainError, match="non-finite"):
        fit(task(tmp_path, 2, Synthetic(nan_at=0), "diffusion.nan_limit=2"), quiet=True)


def test_resume_refuses_other_settings(tmp_path):
    fit(task(tmp_path, 1), quiet=True)
    # pipeline.checkpoint.load_last refuses before loading any weight; the CLI prints its errors
    # as one line (exit status 2), and the message names the setting that changed.
    with pytest.raises(CheckpointError, match=r"different settings \(lr\); delete"):
        fit(task(tmp_path, 1, None, "diffusion.lr=2e-3"), quiet=True)


# ---- save / load --------------------------------------------------------------------------------

def test_base_folder_round_trip_and_diffusers_layout(tmp_path):
    unet, prompt = base_lib.build(TINY_UNET, seed=3)
    base_lib.save(tmp_path / "ours", unet, prompt)
    # A folder as DeepFloyd ships it: diffusers' own save_pretrained, plus the empty-prompt embedding.
    unet.save_pretrained(tmp_path / "if_layout", safe_serialization=True)
    from safetensors.torch import save_file
    save_file({"prompt_embeds": prompt}, str(tmp_path / "if_layout" / base_lib.PROMPT))
    z, noisy, aux, t = inputs()
    with torch.no_grad():
        ref = ControlledDenoiser(unet, prompt, None)(z, noisy, None, t)
        for folder in ("ours", "if_layout"):
            u2, p2 = base_lib.load(tmp_path / folder)
            assert all(torch.equal(a, b) for a, b in zip(unet.state_dict().values(), u2.state_dict().values()))
            assert torch.equal(p2, prompt)
            # Same weights; diffusers' loader can change float summation order by ~1e-6.
            torch.testing.assert_close(ControlledDenoiser(u2, p2, None)(z, noisy, None, t), ref, rtol=1e-5, atol=1e-5)
    (tmp_path / "if_layout" / base_lib.PROMPT).unlink()
    with pytest.raises(CheckpointError, match="prompt_embeds.safetensors: missing"):
        base_lib.load(tmp_path / "if_layout")
    bad = dict(TINY_UNET, in_channels=4, out_channels=4)
    u3, p3 = base_lib.build(bad)
    base_lib.save(tmp_path / "bad", u3, p3)
    with pytest.raises(CheckpointError, match="expected 6/6"):
        base_lib.load(tmp_path / "bad")


# ---- sampler ------------------------------------------------------------------------------------

@pytest.mark.parametrize("skip", [0, 12, 18, 26])
def test_sampler_is_finite_and_deterministic_for_extreme_inputs(skip):
    m = tiny_model().eval()
    H, W = 12, 10   # not a multiple of the base's factor: padded inside
    cases = {
        "zero": np.zeros((H, W, 3), np.float32),
        "clamp": np.full((H, W, 3), 6.0, np.float32),
        "fireflies": np.where(np.random.default_rng(0).random((H, W, 3)) < 0.05, 1e4, 0.01).astype(np.float32),
    }
    for name, color in cases.items():
        x = torch.from_numpy(np.moveaxis(to_model(color), 2, 0))[None]
        aux = torch.from_numpy(condition({"color": color}, 4))[None]
        a = sample(m, x, aux, skip=skip, seed=5)
        b = sample(m, x, aux, skip=skip, seed=5)
        assert a.shape == x.shape and torch.isfinite(a).all(), name
        assert torch.equal(a, b), name


def test_tiled_sampling_covers_the_frame():
    m = tiny_model().eval()
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 3, 40, 56, generator=g) * 2 - 1
    aux = torch.rand(1, AUX_CHANNELS, 40, 56, generator=g)
    out, std = sample_tiled(m, x, aux, tile=24, overlap=8, skip=24, seed=1)
    assert out.shape == x.shape and torch.isfinite(out).all()
    assert torch.equal(std, torch.zeros_like(std))          # one sample: no spread


def test_train_base_option_trains_the_base_too(tmp_path):
    t = task(tmp_path, 1, None, "diffusion.train_base=true")
    m = t.model
    before = {k: v.clone() for k, v in m.base.state_dict().items()}
    fit(t, quiet=True)
    assert any(not torch.equal(before[k], v) for k, v in m.base.state_dict().items())
    assert len(m.trainable_parameters()) == len(list(m.control.parameters())) + len(list(m.base.parameters()))


def test_small_variance_ignores_the_variance_output():
    """variance="small" samples with the posterior variance whatever the network's variance head
    says; the learned-range sampler follows it. An imperfect ε (0.9 × the truth) makes the step
    noise matter: with small variance v = −1 and v = +1 give the same image, with the learned
    range v = +1 (variance β, the largest) leaves the result further from x than v = −1."""
    acp = diffusion.make_scheduler().alphas_cumprod
    x = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(0)) * 1.6 - 0.9

    class Imperfect(torch.nn.Module):
        multiple = 1

        def __init__(self, v):
            super().__init__()
            self.v = v

        def forward(self, z, noisy, aux, t):
            a = acp[t].view(-1, 1, 1, 1)
            return torch.cat([0.9 * (z - a.sqrt() * x) / (1 - a).sqrt(), torch.full_like(z, self.v)], 1)

    def err(v, variance):
        return (sample(Imperfect(v), torch.zeros_like(x), None, skip=0, seed=1, variance=variance) - x).abs().mean()

    assert torch.equal(sample(Imperfect(-1.0), torch.zeros_like(x), None, seed=1, variance="small"),
                       sample(Imperfect(1.0), torch.zeros_like(x), None, seed=1, variance="small"))
    assert err(1.0, "learned") > 1.2 * err(-1.0, "learned")
    with pytest.raises(ValueError, match="sampler variance"):
        sample(Imperfect(0.0), torch.zeros_like(x), None, variance="big")


@pytest.mark.parametrize("skip", [0, 12, 24])
def test_sampler_recovers_the_image_with_an_oracle_model(skip):
    """With the true ε (and the posterior variance), every skip setting must land exactly on x: the
    scheduler wiring, the respaced steps and the q-sampled start are right, whatever the network."""
    acp = diffusion.make_scheduler().alphas_cumprod
    x = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(0)) * 1.6 - 0.9

    class Oracle(torch.nn.Module):
        multiple = 1

        def forward(self, z, noisy, aux, t):
            a = acp[t].view(-1, 1, 1, 1)
            return torch.cat([(z - a.sqrt() * x) / (1 - a).sqrt(), -torch.ones_like(z)], 1)

    out = sample(Oracle(), torch.zeros_like(x), None, skip=skip, seed=1)
    torch.testing.assert_close(out, x, rtol=0, atol=1e-6)
