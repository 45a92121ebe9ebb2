"""oidn_ft (train/baselines/oidn_ft.py): OIDN's network fine-tuned on the store, used by the evaluator, exported
as OIDN weights and run by OIDN itself."""
import json
import shutil

import numpy as np
import pytest
import torch

from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.errors import PipelineError
from mcdenoise.pipeline.store import Store, stack_name
from mcdenoise.train import oidn
from mcdenoise.train.baselines import oidn_ft
from mcdenoise.train.model import LAYERS, LEVEL, load_unet, unet_denoise
from tests.helpers import TINY, cli, train_tiny

FT_TINY = ["oidn_ft.epochs=2", "oidn_ft.crop=16", "oidn_ft.batch_size=2", "oidn_ft.crops_per_frame=2",
           "oidn_ft.warmup_steps=1", "oidn_ft.lr=1e-3", "oidn_ft.device=cpu"]


def tiny(store, runs, *extra):
    return load_config(TINY, [f"store={store}", f"runs={runs}", *FT_TINY, *extra])


@pytest.fixture(scope="module")
def trained(cleaned, tmp_path_factory):
    """One small oidn_ft run on the tiny cleaned store (through the command line)."""
    store, _ = cleaned
    runs = tmp_path_factory.mktemp("oidn_ft") / "runs"
    return store, runs, train_tiny("oidn_ft", store, runs, *FT_TINY, "oidn_ft.distill=0.5", "oidn_ft.l2sp=0.1")


@pytest.mark.slow
def test_training_starts_at_oidn_and_moves_away(trained):
    store, runs, proc = trained
    folder = runs / "oidn_ft_rt_hdr_alb_nrm"
    hist = json.loads((folder / "train.json").read_text())["history"]
    assert [h["epoch"] for h in hist] == [0, 1, 2]
    # epoch 0 is stock OIDN, scored by the twin: exactly OIDN's own score
    assert hist[0]["val"]["psnr"] == hist[0]["val"]["oidn_psnr"]
    assert all(h["val"]["images"] == len(Store(store).frames("val")) * 3 for h in hist)   # 4, 8, 16 spp
    assert all(h["train_loss"] > 0 and h["terms"]["l2sp"] > 0 for h in hist[1:])
    last = oidn_ft.load_run(folder, tiny(store, runs))[0]
    stock = load_unet("rt_hdr_alb_nrm")
    # the last checkpoint moved away from OIDN (whichever epoch was best)
    from safetensors.torch import load_file
    moved = load_file(str(folder / "last.safetensors"))
    assert not torch.equal(moved["model.dec_conv0.weight"], stock.dec_conv0.weight)
    record = json.loads((folder / "model.json").read_text())
    assert record["network"] == "rt_hdr_alb_nrm" and record["spp"] == [4, 8, 16]
    assert record["prior_sha256"] == __import__("hashlib").sha256(oidn.weights_blob("rt_hdr_alb_nrm")).hexdigest()
    assert last.in_channels == 9
    assert "already trained" in cli("train", "--model", "oidn_ft", "--spp", "any", "--config", TINY, f"store={store}",
                                    f"runs={runs}", *FT_TINY, "oidn_ft.distill=0.5", "oidn_ft.l2sp=0.1").stdout


@pytest.mark.slow
def test_exported_weights_run_in_oidn_as_in_the_twin(trained, tmp_path):
    store, runs, _ = trained
    folder = runs / "oidn_ft_rt_hdr_alb_nrm"
    # make the best epoch a trained one, so the comparison is not stock against stock
    shutil.copy(folder / "model.json", tmp_path / "model.json")
    from safetensors.torch import load_file, save_file
    save_file({k[6:]: v for k, v in load_file(str(folder / "last.safetensors")).items() if k.startswith("model.")},
              str(tmp_path / "model.safetensors"))
    run = tmp_path / "runs" / "oidn_ft_rt_hdr_alb_nrm"
    run.mkdir(parents=True)
    for f in ("model.json", "model.safetensors"):
        shutil.move(tmp_path / f, run / f)
    cfg = tiny(store, tmp_path / "runs")
    out = tmp_path / "w" / "mine.tza"
    cli("export", "--format", "oidn", "--config", TINY, f"store={store}", f"runs={tmp_path / 'runs'}", "--out", out)
    assert json.loads(out.with_suffix(".json").read_text())["network"] == "rt_hdr_alb_nrm"
    net = oidn_ft.load_run(run, cfg)[0]
    buf = Store(store).read(*_first(store), 4)
    theirs = oidn.denoise(buf, weights=out.read_bytes())
    ours = unet_denoise(net, buf["color"], buf["albedo"], buf["normal"])
    stock = oidn.denoise(buf)
    assert _psnr(theirs, ours) >= 80 and _psnr(theirs, stock) < 70
    # blend 0 is OIDN's own weights, bit for bit
    assert oidn_ft.export_blob(oidn_ft.load_run(run, cfg, blend=0.0)[0]) == oidn.weights_blob("rt_hdr_alb_nrm")
    # the command line runs them too, and refuses weights that need layers the input lacks
    exr = tmp_path / "in.exr"
    from tests.helpers import write_rgb_exr
    write_rgb_exr(exr, buf["color"])
    bad = cli("denoise", "--exr", exr, "--out", tmp_path / "o.exr", "--oidn-weights", out, check=False)
    assert bad.returncode == 2 and "read 9 channels" in bad.stderr and "has only colour" in bad.stderr
    ok = cli("denoise", "--exr", exr, "--out", tmp_path / "o.exr", "--method", "oidn")
    assert "pyoidn built-in rt_hdr" in ok.stdout and (tmp_path / "o.exr").exists()
    bad = cli("denoise", "--exr", exr, "--out", tmp_path / "p.exr", "--method", "oidn_prefilter", check=False)
    assert bad.returncode == 2 and "has only colour" in bad.stderr and not (tmp_path / "p.exr").exists()


@pytest.mark.slow
def test_the_evaluator_runs_the_run_and_says_what_is_missing(trained, tmp_path, monkeypatch):
    """oidn_ft runs the store's run; the colour-only and colour + albedo rows without a run of their own run
    the weights shipped with the model (what `ours` uses on inputs without normal) on the layers their stock
    rows read, oidn_ft without one the shipped full-layer network, and without those they say what to train."""
    from mcdenoise.evaluate.methods import Loader, MethodUnavailable
    from mcdenoise.train import model as shipped_model
    store, runs, _ = trained
    loader = Loader(tiny(store, runs))
    method = loader.load("oidn_ft", 4)
    buf = Store(store).read(*_first(store), 4)
    best = oidn_ft.load_run(runs / "oidn_ft_rt_hdr_alb_nrm", tiny(store, runs))[0]
    assert _psnr(method.denoise(buf), unet_denoise(best, buf["color"], buf["albedo"], buf["normal"])) >= 80
    for family, layers in (("oidn_ft_color", ("color",)), ("oidn_ft_albedo", ("color", "albedo"))):
        method, stock = loader.load(family, 4), loader.load(family.replace("_ft", ""), 4)
        network = "rt_hdr_alb" if "albedo" in layers else "rt_hdr"
        shipped = shipped_model.SHIPPED_MODEL / "oidn_ft" / f"{network}.tza"
        assert method.checkpoint == f"train/shipped/oidn_ft/{network}.tza"
        only = {k: buf[k] for k in layers}
        out = method.denoise(buf)
        assert np.array_equal(out, oidn.denoise(only, weights=shipped.read_bytes()))
        assert np.array_equal(stock.denoise(buf), oidn.denoise(only))   # the stock row reads the same layers
        assert _psnr(out, stock.denoise(buf)) < 70                      # not stock OIDN's network for them
    # no run of its own: the oidn_ft row runs the shipped full-layer network, as the other two rows do
    method = Loader(tiny(store, tmp_path / "no_runs")).load("oidn_ft", 4)
    shipped = shipped_model.SHIPPED_MODEL / "oidn_ft" / "rt_hdr_alb_nrm.tza"
    assert method.checkpoint == "train/shipped/oidn_ft/rt_hdr_alb_nrm.tza"
    assert np.array_equal(method.denoise(buf), oidn.denoise(buf, weights=shipped.read_bytes()))
    with pytest.raises(MethodUnavailable, match=r"oidn_ft_rt_hdr.*oidn_ft.network=rt_hdr"):   # the switch
        Loader(tiny(store, runs, "diffusion.shipped=false")).load("oidn_ft_color", 4)
    monkeypatch.setattr(shipped_model, "SHIPPED_MODEL", tmp_path / "no_shipped_model")
    with pytest.raises(MethodUnavailable, match=r"oidn_ft_rt_hdr.*oidn_ft.network=rt_hdr"):
        Loader(tiny(store, runs)).load("oidn_ft_color", 4)


def test_trainable_subsets():
    net = load_unet("rt_hdr_small")
    n = sum(p.numel() for p in net.parameters())
    bias = sum(p.numel() for p in oidn_ft.trainable_parameters(net, "bias"))
    decoder = sum(p.numel() for p in oidn_ft.trainable_parameters(net, "decoder"))
    assert bias == sum(net.widths[k][0] for k in LAYERS) and bias < 0.01 * n
    assert 0.3 * n < decoder < n
    assert sum(p.numel() for p in oidn_ft.trainable_parameters(net, "all")) == n


def test_fine_levels_train_only_the_finest_resolutions():
    """'fine' with 2 levels: the layers that see the full and the half-resolution image train, the coarse ones
    (a quarter resolution and below) stay OIDN's bit for bit through an Adam step; the count grows with the
    levels up to every weight."""
    assert sorted(LEVEL) == sorted(LAYERS)        # every layer has its resolution
    net = load_unet("rt_hdr_small")
    prior = {k: v.detach().clone() for k, v in net.named_parameters()}
    params = oidn_ft.trainable_parameters(net, "fine", 2)
    trained = {n.split(".")[0] for n, p in net.named_parameters() if p.requires_grad}
    assert trained == {"enc_conv0", "enc_conv1", "enc_conv2", "dec_conv2a", "dec_conv2b", "dec_conv1a",
                       "dec_conv1b", "dec_conv0"}
    opt = torch.optim.AdamW(params, lr=1e-3)
    x = torch.rand(1, net.in_channels, 32, 32)
    net(x).abs().mean().backward()
    opt.step()
    for name, p in net.named_parameters():
        moved = not torch.equal(p.detach(), prior[name])
        assert moved == (name.split(".")[0] in trained), name
    counts = [sum(p.numel() for p in oidn_ft.trainable_parameters(net, "fine", k)) for k in range(1, 6)]
    assert counts == sorted(set(counts)) and counts[-1] == sum(p.numel() for p in net.parameters())


def test_l2sp_is_zero_at_the_prior_and_grows_with_the_change():
    net = load_unet("rt_hdr_small")
    oidn_ft.trainable_parameters(net, "all")
    ref = {k: v.detach().clone() for k, v in net.named_parameters()}
    assert float(oidn_ft.l2sp_penalty(net, ref).detach()) == 0
    with torch.no_grad():
        net.enc_conv0.weight.mul_(1.1)
    small = float(oidn_ft.l2sp_penalty(net, ref).detach())
    with torch.no_grad():
        net.enc_conv0.weight.mul_(1.1)
    assert 0 < small < float(oidn_ft.l2sp_penalty(net, ref).detach())


def test_learning_rate_warms_up_then_decays_to_its_end():
    lrs = [oidn_ft.lr_at(s, 100, 1e-3, 1e-5, 10) for s in range(100)]
    assert lrs[0] < lrs[5] < lrs[9] == pytest.approx(1e-3)
    assert all(a >= b for a, b in zip(lrs[9:], lrs[10:]))
    assert oidn_ft.lr_at(100, 100, 1e-3, 1e-5, 10) == pytest.approx(1e-5)


def test_augmentation_permutes_colour_and_target_together():
    rng = np.random.default_rng(3)
    colour = rng.random((8, 6, 3)).astype(np.float32)
    images = {"color": colour, "albedo": colour * 0.5, "normal": rng.random((8, 6, 3)), "target": colour * 2}
    for seed in range(8):
        out = oidn_ft._augment(images, np.random.default_rng(seed))
        np.testing.assert_allclose(out["albedo"], out["color"] * 0.5)
        np.testing.assert_allclose(out["target"], out["color"] * 2)
        assert sorted(out["color"].ravel()) == sorted(colour.ravel())
        assert out["color"].shape in ((8, 6, 3), (6, 8, 3))


def test_wrong_settings_are_named():
    with pytest.raises(PipelineError, match="oidn_ft.crop"):
        load_config(None, ["oidn_ft.crop=20"])
    with pytest.raises(PipelineError, match="oidn_ft.network"):
        load_config(None, ["oidn_ft.network=rt_ldr"])
    with pytest.raises(PipelineError, match="oidn_ft.trainable"):
        load_config(None, ["oidn_ft.trainable=encoder"])
    with pytest.raises(PipelineError, match="oidn_ft.target"):
        load_config(None, ["oidn_ft.target=gt2"])
    with pytest.raises(PipelineError, match="oidn_ft.fine_levels"):
        load_config(None, ["oidn_ft.trainable=fine", "oidn_ft.fine_levels=6"])


@pytest.mark.slow
def test_the_target_is_gt_clean_or_the_raw_gt1(cleaned):
    store = Store(cleaned[0])
    key = store.frames_with("train")[0]
    read = {name: store.read_image(key.scene, key.frame, name, ["color"])[0]["color"] for name in ("gt_clean", "gt1")}
    assert not np.array_equal(read["gt_clean"], read["gt1"])
    for name in ("gt_clean", "gt1"):
        np.testing.assert_array_equal(oidn_ft.Frame(store, key, oidn_ft.AUX, name).target, read[name])


def _first(store):
    k = Store(store).frames("val")[0]
    return k.scene, k.frame


def _psnr(a, b):
    ta, tb = a / (1 + a), b / (1 + b)
    mse = float(np.mean((ta.astype(np.float64) - tb) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1 / mse)


def test_relative_l1_counts_each_crop_by_its_gain_over_oidn():
    target = torch.zeros(2, 3, 8, 8)
    stock = torch.stack([torch.full((3, 8, 8), 0.01), torch.full((3, 8, 8), 0.3)])   # an easy and a hard crop
    teacher = torch.tensor([False, False])
    at_oidn = float(oidn_ft.relative_l1(stock, target, stock, teacher))
    better_easy = stock.clone()
    better_easy[0] /= 2
    better_hard = stock.clone()
    better_hard[1] /= 2
    gain_easy = at_oidn - float(oidn_ft.relative_l1(better_easy, target, stock, teacher))
    gain_hard = at_oidn - float(oidn_ft.relative_l1(better_hard, target, stock, teacher))
    assert gain_easy == pytest.approx(gain_hard, rel=0.02) and gain_easy > 0.2
    # a distillation crop (target: OIDN's own output) is weighed like a typical crop of the batch
    mixed = oidn_ft.relative_l1(stock + 0.01, torch.stack([target[0], stock[1]]), stock, torch.tensor([False, True]))
    assert float(mixed) > 0


def test_changed_frames_tint_the_light_not_the_albedo():
    rng = np.random.default_rng(0)
    images = {"color": rng.random((64, 64, 3)).astype(np.float32) + 0.1,
              "albedo": rng.random((64, 64, 3)).astype(np.float32),
              "normal": np.tile(np.array([0, 0, 1], np.float32), (64, 64, 1))}
    images["target"] = images["color"] * 0.9
    for seed in range(6):
        out = oidn_ft._unlike(images, np.random.default_rng(seed), 16)
        gains = (out["color"].reshape(-1, 3).mean(0) / images["color"].reshape(-1, 3).mean(0))
        np.testing.assert_allclose(out["target"], out["color"] * 0.9, rtol=1e-5)
        small = out["color"].shape[0] == 32
        if not small:
            np.testing.assert_array_equal(out["albedo"], images["albedo"])
        assert not np.allclose(gains, gains[0], rtol=1e-3)      # the light's colour changed
        assert np.allclose(np.linalg.norm(out["normal"], axis=2), 1, atol=1e-5)


@pytest.mark.slow
def test_the_final_frame_network_trains_on_prefiltered_aux_and_its_row_runs_it_so(cleaned, tmp_path, monkeypatch):
    """oidn_ft.network=rt_hdr_calb_cnrm_large: training frames and validation read the aux prefiltered by
    OIDN's aux networks, epoch 0 is OIDN's final-frame mode, and the evaluator's oidn_ft_prefilter row runs the
    exported weights in that mode."""
    store, _ = cleaned
    runs = tmp_path / "runs"
    large = ["oidn_ft.network=rt_hdr_calb_cnrm_large", "oidn_ft.epochs=1", "oidn_ft.val_frames=1"]
    s = Store(store)
    key = s.frames_with("train")[0]
    frame = oidn_ft.Frame(s, key, ("albedo", "normal"), clean_aux=True)
    stack = s.read_image(key.scene, key.frame, stack_name(0), ["albedo", "normal"])[0]
    want = oidn.prefilter_aux(stack["albedo"], stack["normal"])
    np.testing.assert_allclose(frame.aux["albedo"][0], want[0], atol=1e-3)   # float16 in memory
    np.testing.assert_allclose(frame.aux["normal"][0], want[1], atol=1e-3)
    assert np.abs(frame.aux["normal"][0] - stack["normal"]).max() > 1e-2     # the prefilter changed them
    cli("train", "--model", "oidn_ft", "--spp", "any", "--config", TINY, f"store={store}", f"runs={runs}",
        *FT_TINY, *large)
    folder = runs / "oidn_ft_rt_hdr_calb_cnrm_large"
    hist = json.loads((folder / "train.json").read_text())["history"]
    assert hist[0]["val"]["psnr"] == hist[0]["val"]["oidn_psnr"]
    from mcdenoise.evaluate.methods import Loader
    cfg = tiny(store, runs, *large, "oidn_ft.blend=0")          # blend 0: OIDN's own weights, exported
    buf = s.read(*_first(store), 4)
    row = Loader(cfg).load("oidn_ft_prefilter", 4)
    assert _psnr(row.denoise(buf), oidn.denoise(buf, clean_aux=True)) > 80
    # exported, its card names the network, and denoise --oidn-weights runs it in the final-frame mode
    tza_file = tmp_path / "large.tza"
    over = [f"store={store}", f"runs={runs}", *FT_TINY, *large, "oidn_ft.blend=0"]
    cli("export", "--format", "oidn", "--config", TINY, *over, "--out", tza_file)
    scene, frame = _first(store)
    for how in (["--oidn-weights", tza_file], ["--method", "oidn_ft_prefilter"]):
        out = tmp_path / f"{how[0][2:]}.exr"
        cli("denoise", "--config", TINY, *over, "--frame", f"{scene}/{frame}", "--spp", "4", "--out", out, *how)
        from mcdenoise.pipeline.exr import read_image
        assert _psnr(read_image(out)[0]["color"], row.denoise(buf)) > 80
