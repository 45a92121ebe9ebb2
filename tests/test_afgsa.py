"""AFGSA (train.baselines.afgsa: the network, its losses, its recipe on clean.train's loop): attention against a
naive reference, finite output on the stability suite's inputs, the L1-only ablation, exact resume."""
import json
import os

import numpy as np
import pytest
import torch

from mcdenoise.clean.data import CHANNELS, IN_CHANNELS, BaselinePairs
from mcdenoise.clean.train import save_best
from mcdenoise.evaluate.methods import Loader, MethodUnavailable, label
from mcdenoise.evaluate.stability import run_stability
from mcdenoise.pipeline.config import load_config, run_dir
from mcdenoise.pipeline.store import Store
from mcdenoise.train.baselines.afgsa import (
    AFGSANet,
    GuidedAttention,
    PatchCritic,
    afgsa_recipe,
    branch_channels,
    critic_loss,
    generator_loss,
    load_model,
    log_radiance,
    train,
    window_attention,
)
from mcdenoise.train.baselines.afgsa_report import fine_energy
from tests.helpers import TINY, make_clean_store

# A network that runs in a fraction of a second on the tiny store.
TINY_NET = ["afgsa.channels=8", "afgsa.extractor_channels=4", "afgsa.blocks=1", "afgsa.heads=2",
            "afgsa.block_size=4", "afgsa.halo=1", "afgsa.critic_channels=4", "afgsa.critic_levels=2"]


def naive_window_attention(q, k, v, heads, block, halo, key_position=None):
    """Pixel by pixel: each pixel attends to the pixels of the image inside its block's
    (block + 2 halo)^2 window, softmax of scaled dot products (the definition, no unfold)."""
    B, C, H, W = q.shape
    d = C // heads
    out = torch.zeros_like(v)
    for y in range(H):
        for x in range(W):
            y0, x0 = (y // block) * block - halo, (x // block) * block - halo
            ys = [j for j in range(y0, y0 + block + 2 * halo) if 0 <= j < H]
            xs = [i for i in range(x0, x0 + block + 2 * halo) if 0 <= i < W]
            for h in range(heads):
                c = slice(h * d, (h + 1) * d)
                keys = torch.stack([k[:, c, j, i] + (0 if key_position is None else key_position[j - y0, i - x0])
                                    for j in ys for i in xs], 1)                       # (B, n, d)
                vals = torch.stack([v[:, c, j, i] for j in ys for i in xs], 1)
                w = torch.softmax((keys @ q[:, c, y, x, None])[..., 0] / d ** 0.5, dim=1)   # (B, n)
                out[:, c, y, x] = (w[..., None] * vals).sum(1)
    return out


@pytest.mark.slow
def test_window_attention_matches_the_definition_at_any_size():
    torch.manual_seed(0)
    q, k, v = (torch.randn(2, 8, 11, 7) for _ in range(3))         # not a multiple of the block
    pos = torch.randn(4 + 2 * 2, 4 + 2 * 2, 4)
    got = window_attention(q, k, v, heads=2, block=4, halo=2, key_position=pos)
    torch.testing.assert_close(got, naive_window_attention(q, k, v, 2, 4, 2, pos), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("halo", [0, 3])
def test_window_attention_on_a_single_window_is_full_attention(halo):
    """One block covering the whole 6x5 image: every pixel attends to every pixel (the halo's
    out-of-image keys are masked, not zeros that would still take softmax weight)."""
    torch.manual_seed(1)
    q, k, v = (torch.randn(1, 4, 6, 5) for _ in range(3))
    got = window_attention(q, k, v, heads=1, block=8, halo=halo)
    qf, kf, vf = (t.flatten(2)[0].T for t in (q, k, v))                # (30, 4)
    full = (torch.softmax(qf @ kf.T / 2.0, dim=1) @ vf).T.reshape(1, 4, 6, 5)
    torch.testing.assert_close(got, full, rtol=1e-4, atol=1e-5)


def test_guided_attention_with_identical_features_is_plain_self_attention():
    """attend(x, guide=x): queries, keys and values all from x, i.e. plain (windowed) self-attention."""
    torch.manual_seed(2)
    att = GuidedAttention(channels=8, heads=2, block=4, halo=1)
    x = torch.randn(1, 8, 8, 8)
    with torch.no_grad():
        got = att.attend(x, x)
        plain = naive_window_attention(att.q(x), att.k(x), att.v(x), 2, 4, 1, att.key_position())
    torch.testing.assert_close(got, plain, rtol=1e-4, atol=1e-5)


def test_the_guide_picks_the_weights_and_the_noisy_features_are_averaged():
    """With a constant guide and no position term every key looks the same: each pixel gets the
    plain mean of the values over its window. And the guide alone decides the weights: values from
    x, so a different guide gives another filter of the same x."""
    torch.manual_seed(3)
    att = GuidedAttention(channels=4, heads=1, block=8, halo=0)
    with torch.no_grad():
        att.pos_row.zero_(), att.pos_col.zero_()
        x = torch.randn(1, 4, 8, 8)
        out = att.attend(x, torch.ones(1, 4, 8, 8))
        mean = att.v(x).mean(dim=(2, 3), keepdim=True).expand_as(out)
        torch.testing.assert_close(out, mean, rtol=1e-5, atol=1e-6)
        assert not torch.allclose(att.attend(x, torch.randn(1, 4, 8, 8)), mean, atol=1e-3)


def test_branches_split_the_project_encoding():
    noisy, aux, colour = branch_channels()
    assert sorted(noisy + aux) == list(range(IN_CHANNELS)) and not set(noisy) & set(aux)
    assert colour == slice(0, 3) and CHANNELS[0][0] == "color"
    names = [k for k, n, _ in CHANNELS for _ in range(n)]
    assert {names[i] for i in aux} >= {"albedo", "normal", "depth", "albedo.variance"}
    assert {names[i] for i in noisy} >= {"color", "diffuse_indirect", "color.variance"}


def test_output_is_at_most_twice_the_brightest_noisy_pixel_nearby():
    """An overshooting network (head bias +5 in log space, x150) is held to 2 m + 1, m the brightest
    noisy colour within BOUND_RADIUS of the pixel; the raw log-space output (what the losses see)
    is not clamped."""
    from mcdenoise.train.baselines.afgsa import BOUND_RADIUS

    torch.manual_seed(7)
    net = AFGSANet(IN_CHANNELS, channels=8, extractor_channels=4, blocks=1, block_size=4, halo=1).eval()
    with torch.no_grad():
        net.head[-1].bias.fill_(5.0)
        inputs = torch.zeros(1, IN_CHANNELS, 40, 40)
        colour = torch.zeros(1, 3, 40, 40)
        colour[..., 10, 10] = 100.0                              # one bright pixel in a black frame
        inputs[:, :3] = torch.log1p(colour)
        out = net(inputs, colour)
        assert float(net.log_forward(inputs).min()) > 4.0        # raw: e^5 - 1 ≈ 147 everywhere
    near = out[..., 10 - BOUND_RADIUS:11 + BOUND_RADIUS, 10 - BOUND_RADIUS:11 + BOUND_RADIUS]
    assert float(near.max()) <= 201.0 + 1e-3                          # 2·100 + 1
    torch.testing.assert_close(out[..., 10, 10], torch.full((1, 3), 201.0))   # raw: 101·e^5 - 1
    far = out.clone()
    far[..., 10 - BOUND_RADIUS:11 + BOUND_RADIUS, 10 - BOUND_RADIUS:11 + BOUND_RADIUS] = 1.0
    torch.testing.assert_close(far, torch.ones_like(far))           # no bright pixel nearby: 2·0 + 1

def test_adversarial_weight_zero_is_the_l1_only_loss():
    fake, real = torch.rand(2, 3, 8, 8), torch.rand(2, 3, 8, 8)

    def no_critic(_):
        raise AssertionError("the critic must not be used at weight 0")

    loss, terms = generator_loss(fake, real, no_critic, 0.0)
    assert float(loss) == pytest.approx(float((fake - real).abs().mean())) and set(terms) == {"l1"}
    critic = PatchCritic(4, 1)
    loss_adv, terms = generator_loss(fake, real, critic, 0.5)
    assert float(loss_adv.detach()) == pytest.approx(float(loss) - 0.5 * float(critic(fake).mean().detach()))


@pytest.mark.slow
def test_weight_zero_step_is_an_l1_step_and_leaves_the_critic(tmp_path):
    """One recipe step at adv_weight 0 moves the generator exactly as Adam on the L1 loss alone does
    and never touches the critic."""
    cfg = load_config(None, [*TINY_NET, "afgsa.adv_weight=0", "afgsa.device=cpu", f"runs={tmp_path}"])
    recipe = afgsa_recipe(cfg, 4)
    twin = afgsa_recipe(cfg, 4)                            # same seed: same initial weights
    critic_before = {k: v.clone() for k, v in recipe.state["critic"].state_dict().items()}
    torch.manual_seed(5)
    batch = {"inputs": torch.rand(2, IN_CHANNELS, 8, 8), "radiance": torch.rand(2, 3, 8, 8),
             "target": torch.rand(2, 3, 8, 8)}
    terms, ok = recipe.step(batch, torch.Generator().manual_seed(0))
    assert ok and set(terms) == {"loss"}
    g = twin.model
    opt = torch.optim.Adam(g.parameters(), lr=cfg.afgsa.lr)
    loss = (g.log_forward(batch["inputs"]) - log_radiance(batch["target"])).abs().mean()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(list(g.parameters()), cfg.afgsa.grad_clip)
    opt.step()
    assert terms["loss"] == pytest.approx(float(loss.detach()))
    for (name, a), b in zip(recipe.model.state_dict().items(), g.state_dict().values()):
        assert torch.equal(a, b), name
    for k, v in recipe.state["critic"].state_dict().items():
        assert torch.equal(v, critic_before[k]), k


@pytest.mark.slow
def test_critic_loss_prefers_the_target_after_training():
    """The WGAN-GP critic learns to score real (smooth) crops above fake (noisy) ones."""
    torch.manual_seed(6)
    critic = PatchCritic(4, 2)
    opt = torch.optim.Adam(critic.parameters(), lr=1e-2)
    real = torch.full((4, 3, 16, 16), 0.5)
    fake = real + 0.3 * torch.randn(4, 3, 16, 16)
    gen = torch.Generator().manual_seed(0)
    first = critic_loss(critic, real, fake, 10.0, gen)[1]["wasserstein"]
    for _ in range(30):
        loss, terms = critic_loss(critic, real, fake, 10.0, gen)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert terms["wasserstein"] > max(first, 0.0) + 0.05 and np.isfinite(terms["gp"])


# ---- training on the tiny store ----------------------------------------------------------------


@pytest.fixture(scope="module")
def store_root(tmp_path_factory):
    return make_clean_store(tmp_path_factory.mktemp("afgsa") / "store")


def afgsa_cfg(root, **keys):
    overrides = [f"store={root / 'store'}", f"runs={root / 'runs'}", *TINY_NET, "afgsa.target=gt1",
                 "afgsa.epochs=2", "afgsa.batch_size=2", "afgsa.crop=8", "afgsa.crops_per_frame=2",
                 "afgsa.device=cpu"]
    return load_config(None, overrides + [f"afgsa.{k}={v}" for k, v in keys.items()])


def _linked(tmp_path, store_root, name):
    d = tmp_path / name
    d.mkdir()
    os.symlink(store_root, d / "store")
    return d


@pytest.mark.slow
def test_training_writes_a_loadable_run_and_resumes_exactly(tmp_path, store_root):
    """Two epochs in one go and 1 + 1 epochs (a rerun resuming the checkpoint) give bitwise the same
    generator, critic and optimizer state; the best weights load through train.baselines.afgsa.load_model."""
    a, b = _linked(tmp_path, store_root, "a"), _linked(tmp_path, store_root, "b")
    train(afgsa_cfg(a), 4, quiet=True)
    train(afgsa_cfg(b, epochs=1), 4, quiet=True)
    assert train(afgsa_cfg(b), 4, quiet=True)["trained_epochs"] == 1
    from safetensors.torch import load_file
    folder = run_dir(afgsa_cfg(a), "afgsa", 4)
    assert folder.name == "afgsa_gt1_spp4"
    wa, wb = (load_file(str(d / "runs" / folder.name / "last.safetensors")) for d in (a, b))
    assert wa.keys() == wb.keys() and any(k.startswith("optim.critic.") for k in wa)
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    hist = json.loads((folder / "train.json").read_text())["history"]
    assert len(hist) == 2 and set(hist[0]["terms"]) == {"adv", "wasserstein", "gp"}
    assert all(np.isfinite(h["train_loss"]) and h["skipped_steps"] == 0 for h in hist)
    model, meta = load_model(folder)
    assert isinstance(model, AFGSANet) and meta["target"] == "gt1" and meta["format"] == "mcdenoise-afgsa"
    assert (folder / "loss.png").stat().st_size > 1000


def test_a_non_finite_target_is_skipped_then_stops_the_run(tmp_path, store_root, monkeypatch):
    """The NaN guard: non-finite steps are skipped without touching the weights; nan_limit of them in
    a row end the run with an error naming the cause."""
    d = _linked(tmp_path, store_root, "nan")
    real = BaselinePairs.__getitem__

    def poisoned(self, index):
        item = real(self, index)
        if self.train:
            item["target"][0, 0, 0] = float("nan")
        return item

    monkeypatch.setattr(BaselinePairs, "__getitem__", poisoned)
    with pytest.raises(RuntimeError, match="2 steps in a row had a non-finite loss"):
        train(afgsa_cfg(d, nan_limit=2), 4, quiet=True)
    assert not (run_dir(afgsa_cfg(d), "afgsa", 4) / "last.safetensors").exists()


def test_any_spp_draws_every_count_and_validates_each(store_root):
    store = Store(store_root)
    val = BaselinePairs(store, store.frames("val"), [4, 8], crop=None, target="gt1")
    assert len(val) == 2 * len(store.frames("val"))
    # 8 spp pools both stacks of the tiny store: less noise than 4 spp against the same target
    err = [float((val[i]["radiance"] - val[i]["target"]).abs().mean()) for i in (0, 1)]
    assert err[1] < err[0]
    tr = BaselinePairs(store, store.frames("train"), [4, 8], crop=8, crops_per_frame=8, seed=0)
    assert len(tr) == 8 * len(store.frames("train"))


# ---- evaluation ----------------------------------------------------------------------------------


def _save_untrained(folder):
    torch.manual_seed(0)
    model = AFGSANet(IN_CHANNELS, channels=8, extractor_channels=4, blocks=1, block_size=4, halo=1)
    save_best(folder, model, {"hparams": model.hparams}, "afgsa")


def test_eval_loads_afgsa_and_says_why_it_cannot(tmp_path):
    cfg = load_config(None, [f"runs={tmp_path}", "eval.device=cpu"])
    with pytest.raises(MethodUnavailable, match=r"no AFGSA checkpoint.*make train MODEL=afgsa SPP=16"):
        Loader(cfg).load("afgsa", 16)
    _save_untrained(tmp_path / "afgsa_sppany")
    method = Loader(cfg).load("afgsa", 16)           # falls back to the all-spp run
    assert method.name == "afgsa" and isinstance(method.model, AFGSANet)
    assert "afgsa" in cfg.eval.methods and label("afgsa").startswith("AFGSA")


@pytest.mark.slow
def test_stability_suite_runs_afgsa_finite_on_every_case(tmp_path):
    """The generator's output is finite on every small case of make stability (NaN/Inf repaired by
    the harness, 1e5, all black, fireflies, sizes down to 8x8), with its run time; 1e5 stays in the
    1e5 range (at most twice the brightest input nearby, plus 1)."""
    _save_untrained(tmp_path / "runs" / "afgsa_spp4")
    cfg = load_config(TINY, [f"runs={tmp_path / 'runs'}", "eval.methods=[noisy, afgsa]", "eval.device=cpu"])
    data = run_stability(cfg, large=False, out=tmp_path / "r", quiet=True)
    for case, row in data["results"].items():
        cell = row["afgsa"]
        assert cell["status"] == "ok" and cell["seconds"] > 0, (case, cell)
        assert cell["out_min"] >= 0 and np.isfinite(cell["out_max"])
    assert 1e4 < data["results"]["radiance_1e5"]["afgsa"]["out_mean"] <= 2e5 + 1
    assert data["results"]["size_33x17"]["afgsa"]["shape"] == [17, 33, 3]
    assert "`afgsa`" in (tmp_path / "r" / "stability.md").read_text()


# ---- the GT_clean-vs-GT1 report ------------------------------------------------------------------


def test_fine_energy_sees_noise_not_smooth_ramps():
    yy, xx = np.mgrid[0:32, 0:32] / 32.0
    ramp = np.repeat((0.2 + 0.5 * xx + 0.2 * yy)[..., None], 3, axis=2)
    noisy = ramp * (1 + 0.1 * np.random.default_rng(0).standard_normal(ramp.shape))
    assert fine_energy(ramp) < 0.01 * fine_energy(noisy)       # a ramp is (almost) all large scale
    assert fine_energy(np.zeros((4, 4, 3))) == 0.0


@pytest.mark.slow
def test_afgsa_report_scores_both_targets_against_gt_clean(tmp_path, store_root):
    """Both runs (GT_clean and GT1 targets) load, the GT1 row is GT1's own metrics against GT_clean,
    and the crop grid is a picture. The tiny store's gt_clean is written here: the mean of GT1 and GT2."""
    from PIL import Image

    from mcdenoise.pipeline.metrics import all_metrics
    from mcdenoise.train.baselines.afgsa_report import run_afgsa_report

    root = _linked(tmp_path, store_root, "report")
    store = Store(root / "store")
    for key in store.frames():
        g1, g2 = (store.read_image(key.scene, key.frame, n, ["color"])[0]["color"] for n in ("gt1", "gt2"))
        if not store.image_path(key.scene, key.frame, "gt_clean").exists():
            store.write_image(key.scene, key.frame, "gt_clean", {"color": (g1 + g2) / 2, "color.variance": 0 * g1},
                              meta={"image": "gt_clean", "scene": key.scene, "frame": key.frame})
    for target in ("gt_clean", "gt1"):
        train(afgsa_cfg(root, epochs=1, target=target), 4, quiet=True)
    cfg = load_config(None, [f"store={root / 'store'}", f"runs={root / 'runs'}", "eval.split=val", "afgsa.device=cpu"])
    r = run_afgsa_report(cfg, spp=4, out=str(tmp_path / "out"), crops=2)
    keys = store.frames("val")
    read = lambda k, n: store.read_image(k.scene, k.frame, n, ["color"])[0]["color"]
    assert r["frames"] == len(keys) == 2
    assert r["rows"]["GT1"]["psnr"] == pytest.approx(np.mean([all_metrics(read(k, "gt1"), read(k, "gt_clean"))["psnr"]
                                                              for k in keys]))
    assert list(r["rows"]) == ["noisy input", "AFGSA -> GT_clean", "AFGSA -> GT1", "GT1"]
    assert r["rows"]["noisy input"]["fine_energy_ratio"] > r["rows"]["GT1"]["fine_energy_ratio"] > 1
    assert r["training"]["AFGSA -> GT1"]["epochs"] == 1
    md = (tmp_path / "out" / "afgsa_targets.md").read_text()
    assert "| AFGSA -> GT1 |" in md and "afgsa_gt1_spp4" in md
    with Image.open(tmp_path / "out" / "afgsa_targets_crops.png") as im:
        assert im.size[0] > im.size[1] > 100 and np.asarray(im.convert("L")).std() > 5


@pytest.mark.slow
def test_spp_any_trains_one_run_for_every_count(tmp_path, store_root):
    d = _linked(tmp_path, store_root, "any")
    summary = train(afgsa_cfg(d, epochs=1), "any", quiet=True)
    assert summary["folder"].endswith("afgsa_gt1_sppany") and summary["epochs"] == 1
    assert json.loads((d / "runs" / "afgsa_gt1_sppany" / "model.json").read_text())["spp"] == "any"


def test_wall_seconds_adds_the_invocations_of_a_resumed_run():
    from mcdenoise.clean.train import wall_seconds

    # 2 epochs in one invocation (10 s, 20 s), then 2 more after a resume (5 s, 15 s)
    assert wall_seconds([{"seconds": s} for s in (10, 20, 5, 15)]) == 35
    assert wall_seconds([{"seconds": s} for s in (10, 20)]) == 20 and wall_seconds([]) == 0
