"""The denoiser shipped in train/shipped: in the repository, small, documented, and it denoises."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.evaluate.stability import synthetic_buffers
from mcdenoise.pipeline.config import BASE_NETWORKS
from mcdenoise.pipeline.exr import read_image
from mcdenoise.pipeline.store import sha256
from mcdenoise.train import infer, model as tmodel
from mcdenoise.train.infer import load_denoiser
from mcdenoise.train.model import SHIPPED_MODEL
from tests.helpers import cornell_box, write_rgb_exr

ROOT = Path(__file__).resolve().parents[1]


def _mse(a, b):
    return float(np.mean((np.asarray(a, np.float64) - b) ** 2))


def test_shipped_model_is_in_the_repository_small_and_documented():
    files = [p for p in SHIPPED_MODEL.rglob("*") if p.is_file()]
    assert sum(p.stat().st_size for p in files) <= 30 * 2**20
    meta = json.loads((SHIPPED_MODEL / "model.json").read_text())
    # a Control Module on OIDN's own network (its frozen weights in base.tza, checked against model.json)
    assert meta["format"] == tmodel.FORMAT and meta["base_network"] in BASE_NETWORKS
    assert 0 <= meta.get("strength", 1.0) <= 1
    assert sha256(SHIPPED_MODEL / "base.tza") == meta["base_sha256"] and {4, 16, 64} <= set(meta["spp"])
    card = (SHIPPED_MODEL / "README.md").read_text()
    assert "configs/ship.yaml" in card and "python -m pipeline" in card


@pytest.fixture(scope="module")
def shipped():
    return load_denoiser(SHIPPED_MODEL, device="cpu")


@pytest.mark.parametrize("spp", [4, 16, 64])
def test_shipped_model_denoises_a_tiny_frame(shipped, spp):
    """Finite output, closer to the noise-free image than the noisy input, at every spp it serves."""
    truth = synthetic_buffers(40, 48, seed=spp, noise=0.0)["color"]
    noisy = synthetic_buffers(40, 48, seed=spp, noise=0.7)
    out = shipped.denoise(noisy, spp=spp, seed=1)
    assert out.shape == truth.shape and out.dtype == np.float32 and np.isfinite(out).all()
    assert _mse(out, truth) < 0.5 * _mse(noisy["color"], truth)


def test_shipped_model_samples_give_a_mean_and_a_spread(shipped):
    noisy = synthetic_buffers(32, 32, seed=5, noise=0.7)
    one, std1 = shipped.denoise(noisy, spp=4, seed=2, samples=1, with_std=True)
    mean, std = shipped.denoise(noisy, spp=4, seed=2, samples=3, steps=3, with_std=True)
    assert np.all(std1 == 0) and np.all(std >= 0) and np.isfinite(mean).all()
    assert std.max() > 0        # a trained network's samples differ (an untrained one returns its estimate)


def test_output_beyond_oidns_range_is_clamped_and_counted_not_inf(shipped, monkeypatch):
    """A model output past the end of OIDN's output space (where the inverse transfer overflows) ends at the
    range's top (65504 after exposure), counted; an ordinary frame touches none."""
    from mcdenoise.train.model import autoexposure

    frame = synthetic_buffers(32, 32, seed=5, noise=0.7)
    shipped.denoise(frame, spp=4)
    assert shipped.last_clamped == 0
    real = infer.sample

    def past_the_end(model, x, *args):      # the first rows pushed past OIDN's range, as a wild input could
        mean, std, rest = real(model, x, *args)
        mean[..., :4, :] += 2.0
        return mean, std, rest

    monkeypatch.setattr(infer, "sample", past_the_end)
    out = shipped.denoise(frame, spp=4)
    assert np.isfinite(out).all() and shipped.last_clamped >= 4 * 32
    assert out.max() <= 65504.0 / autoexposure(frame["color"]) * 1.0001


def test_garbage_normals_are_shortened_counted_and_give_an_ordinary_image(shipped):
    """Normals of length ~1e3 (the stability suite's bad_normals) are scaled to unit length before the model sees
    them, counted; the output stays near the base's (no blown-up pixels); rendered normals are untouched."""
    from mcdenoise.evaluate.stability import CASES
    bad = CASES["bad_normals"][1]()
    out = shipped.denoise(bad, spp=4)
    assert shipped.last_shortened > 0 and shipped.last_clamped == 0
    base = load_denoiser(SHIPPED_MODEL, device="cpu", base_only=True).denoise(bad, spp=4)
    assert abs(out.mean() - base.mean()) < 0.1 * base.mean()
    shipped.denoise(synthetic_buffers(32, 32, seed=5, noise=0.7), spp=4)
    assert shipped.last_shortened == 0


@pytest.mark.parametrize("layers", [("color",), ("color", "albedo")])
def test_inputs_without_normal_run_the_shipped_oidn_ft_network_for_their_layers(shipped, layers):
    """R,G,B alone and R,G,B + albedo (no normal) get OIDN's network for those layers fine-tuned on the ship
    data (train/shipped/oidn_ft/<network>.tza, card beside it), run by OIDN itself, not stock OIDN."""
    from mcdenoise.train import oidn
    blob = SHIPPED_MODEL / "oidn_ft" / f"{oidn.network_for('albedo' in layers, False)}.tza"
    noisy = {k: v for k, v in synthetic_buffers(40, 48, seed=3, noise=0.7).items() if k in layers}
    out = shipped.denoise(noisy, spp=4)
    assert shipped.last_estimate_only and shipped.fallback == str(blob)
    assert np.array_equal(out, oidn.denoise(noisy, weights=blob.read_bytes()))
    stock = oidn.denoise(noisy)
    assert np.abs(out - stock).max() > 1e-3 * np.abs(stock).max()      # the fine-tuned weights, not OIDN's own


@pytest.mark.parametrize("network", ["rt_hdr", "rt_hdr_alb", "rt_hdr_alb_nrm"])
def test_each_of_oidns_networks_ships_fine_tuned_with_its_card(network):
    """train/shipped/oidn_ft has OIDN's three networks fine-tuned on the ship data (what `ours` runs without
    normal, and the oidn_ft rows and `denoise --oidn-weights` without a run of one's own); each card names
    its network, the file's sha256, its blend and the command that made it, and OIDN's reader takes the file."""
    from mcdenoise.pipeline.weights import read_tza
    from mcdenoise.train.model import UNet
    blob = SHIPPED_MODEL / "oidn_ft" / f"{network}.tza"
    card = json.loads(blob.with_suffix(".json").read_text())
    assert card["network"] == network and card["sha256"] == sha256(blob) and 0 < card["blend"] <= 1
    assert f"oidn_ft.network={network}" in card["exported"]["command"] and f"oidn_ft.blend={card['blend']:g}" in \
        card["exported"]["command"]
    net = UNet.from_tza(read_tza(blob.read_bytes(), str(blob)))
    assert net.in_channels == {"rt_hdr": 3, "rt_hdr_alb": 6, "rt_hdr_alb_nrm": 9}[network]


@pytest.mark.slow
def test_denoise_exr_uses_the_shipped_model_by_default(tmp_path):
    """`python -m mcdenoise denoise --exr IN --out OUT` from another folder with nothing trained (the command
    an installed package gives; the checkout is on PYTHONPATH): an R,G,B EXR comes out denoised."""
    truth = synthetic_buffers(32, 40, seed=7, noise=0.0)["color"]
    noisy = synthetic_buffers(32, 40, seed=7, noise=0.7)["color"]
    src, dst = tmp_path / "in.exr", tmp_path / "out.exr"
    write_rgb_exr(src, noisy)
    env = os.environ | {"PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.run([sys.executable, "-m", "mcdenoise", "denoise", "--exr", str(src), "--out", str(dst),
                           f"runs={tmp_path / 'no_runs'}"], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    out = read_image(dst)[0]["color"]
    assert np.isfinite(out).all() and _mse(out, truth) < 0.5 * _mse(noisy, truth)


@pytest.mark.slow
def test_denoise_without_a_config_runs_the_shipped_model_and_names_the_weights(tmp_path):
    """A runs folder where the command runs (runs/default, a model trained on data/default) is not used without
    --config: the shipped model is, and the summary line and the output's header say which weights ran; with a
    config of that store, its run is."""
    import json
    import shutil

    from mcdenoise.pipeline.exr import read_header
    from mcdenoise.train.model import SHIPPED_MODEL

    run = tmp_path / "runs" / "default" / "diffusion_sppany"
    shutil.copytree(SHIPPED_MODEL, run)
    record = json.loads((run / "model.json").read_text())
    (run / "model.json").write_text(json.dumps({**record, "store": "data/default"}))
    (tmp_path / "mine.yaml").write_text("store: data/default\n")
    write_rgb_exr(tmp_path / "in.exr", synthetic_buffers(32, 40, seed=7, noise=0.7)["color"])
    env = os.environ | {"PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    for extra, weights in (([], f"{SHIPPED_MODEL} (Control Module on OIDN"),
                           (["--config", "mine.yaml"], "runs/default/diffusion_sppany (Control Module on OIDN")):
        proc = subprocess.run([sys.executable, "-m", "mcdenoise", "denoise", "--exr", "in.exr", "--out", "out.exr",
                               "--spp", "4", *extra], cwd=tmp_path, capture_output=True, text=True, env=env)
        assert proc.returncode == 0, proc.stderr
        assert f"with {weights}" in proc.stdout and read_header(tmp_path / "out.exr")["weights"].startswith(weights)

@pytest.mark.slow
def test_denoise_exr_warns_when_a_wide_reconstruction_filter_correlated_the_noise(tmp_path):
    """Mitsuba's default film filter (gaussian) splats samples over neighbours; OIDN leaves such noise in
    place, so `denoise --exr` says so and how to render instead; a box-filtered render gets no warning."""
    env = os.environ | {"PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    for rfilter, warned in (("gaussian", True), ("box", False)):
        src, dst = tmp_path / f"{rfilter}.exr", tmp_path / f"{rfilter}_out.exr"
        write_rgb_exr(src, cornell_box(rfilter))
        proc = subprocess.run([sys.executable, "-m", "mcdenoise", "denoise", "--exr", str(src), "--out", str(dst),
                               "--spp", "4", f"runs={tmp_path / 'no_runs'}"], cwd=tmp_path, capture_output=True,
                              text=True, env=env)
        assert proc.returncode == 0 and dst.exists(), proc.stderr
        assert ("spatially correlated" in proc.stderr and 'rfilter type="box"' in proc.stderr) == warned, proc.stderr


def test_denoise_self_ensemble_is_recorded_and_averages_flipped_copies(tmp_path):
    """`denoise --ensemble 4`: the mean over flipped/transposed copies, still a denoised image, not the plain output."""
    from mcdenoise.pipeline.config import load_config
    from mcdenoise.pipeline.exr import read_header
    from mcdenoise.train.infer import cmd_denoise

    truth = synthetic_buffers(32, 40, seed=8, noise=0.0)["color"]
    noisy = synthetic_buffers(32, 40, seed=8, noise=0.7)["color"]
    write_rgb_exr(tmp_path / "in.exr", noisy)
    cfg = load_config(None, [f"runs={tmp_path / 'no_runs'}", "diffusion.device=cpu"])
    outs = {}
    for n in (1, 4):
        assert cmd_denoise(cfg, 4, None, str(tmp_path / "in.exr"), str(tmp_path / f"out{n}.exr"), None, None,
                           quiet=True, ensemble=n) == 0
        outs[n] = read_image(tmp_path / f"out{n}.exr")[0]["color"]
        assert read_header(tmp_path / f"out{n}.exr")["ensemble"] == n
    assert np.isfinite(outs[4]).all() and _mse(outs[4], truth) < 0.5 * _mse(noisy, truth)
    assert not np.array_equal(outs[1], outs[4]) and _mse(outs[1], outs[4]) < 0.1 * _mse(noisy, truth)


def _on_a_fine_tuned_base(tmp_path: Path, blend: float) -> tuple[Path, Path]:
    """(the shipped model on another base of its network, that base's file): OIDN's weights moved by a fixed
    random change, standing for OIDN + ``blend`` x a fine-tuning (the card beside the file says so), put in
    by ``export --base``; whatever base the shipped model has, the base tests below start from this."""
    from mcdenoise.pipeline.weights import TZATensor, read_tza, write_tza
    from mcdenoise.train import oidn
    from tests.helpers import cli

    network = json.loads((SHIPPED_MODEL / "model.json").read_text())["base_network"]
    rng = np.random.default_rng(0)
    moved = {k: TZATensor((t.array.astype(np.float32) * (1 + 0.05 * rng.standard_normal(t.array.shape)))
                           .astype(np.float16), t.layout) for k, t in read_tza(oidn.weights_blob(network)).items()}
    base = tmp_path / "fine_tuned.tza"
    base.write_bytes(write_tza(moved))
    base.with_suffix(".json").write_text(json.dumps({"network": network, "blend": blend}))
    out = tmp_path / "on_fine_tuned"
    cli("export", "--from", SHIPPED_MODEL, "--base", base, "--out", out, "--quiet")
    return out, base


def test_export_dates_follow_source_date_epoch(monkeypatch):
    """A model folder's dates are SOURCE_DATE_EPOCH's when it is set (UTC), today's otherwise; a value that
    is not whole seconds is a one-line error naming the variable."""
    import datetime

    from mcdenoise.pipeline.errors import ConfigError
    from mcdenoise.train.export import _today

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1764892799")       # 2025-12-04 23:59:59 UTC
    assert _today() == "2025-12-04"
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1764892800")
    assert _today() == "2025-12-05"
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    with pytest.raises(ConfigError, match="SOURCE_DATE_EPOCH='yesterday': expected whole seconds"):
        _today()
    monkeypatch.delenv("SOURCE_DATE_EPOCH")
    before, got, after = datetime.date.today().isoformat(), _today(), datetime.date.today().isoformat()
    assert got in {before, after}


@pytest.mark.slow
def test_export_moves_the_base_of_an_exported_model_and_keeps_its_control_module(tmp_path):
    """export --base-blend: OIDN + b x what fine-tuning changed, from a base recorded at blend a."""
    from mcdenoise.pipeline.weights import read_tza
    from mcdenoise.train import oidn
    from tests.helpers import cli

    a = 0.5
    model, _ = _on_a_fine_tuned_base(tmp_path, a)
    meta = json.loads((model / "model.json").read_text())
    assert meta["base_blend"] == a
    same = tmp_path / "same"
    cli("export", "--from", model, "--base-blend", str(a), "--out", same, "--quiet")
    assert (same / "base.tza").read_bytes() == (model / "base.tza").read_bytes()
    half = tmp_path / "half"
    cli("export", "--from", model, "--base-blend", str(a / 2), "--out", half, "--quiet")
    stock = read_tza(oidn.weights_blob(meta["base_network"]))
    old, new = read_tza((model / "base.tza").read_bytes()), read_tza((half / "base.tza").read_bytes())
    moved = 0
    for name, t in new.items():
        s, o = stock[name].array.astype(np.float32), old[name].array.astype(np.float32)
        assert t.array.dtype == np.float16 and t.layout == old[name].layout
        np.testing.assert_allclose(t.array.astype(np.float32), s + 0.5 * (o - s), rtol=2e-3, atol=1e-4)
        moved += int((t.array != old[name].array).sum())
    assert moved > 0
    record = json.loads((half / "model.json").read_text())
    assert record["base_blend"] == a / 2 and record["base_sha256"] == sha256(half / "base.tza")
    assert (half / "control.safetensors").read_bytes() == (SHIPPED_MODEL / "control.safetensors").read_bytes()
    assert "--base-blend" in (half / "README.md").read_text()
    # back to OIDN itself (blend 0): stock OIDN's weights exactly, and the folder still loads
    zero = tmp_path / "zero"
    cli("export", "--from", half, "--base-blend", "0", "--out", zero, "--quiet")
    back = read_tza((zero / "base.tza").read_bytes())
    assert all(np.array_equal(back[k].array, stock[k].array) for k in stock)
    tmodel.load(zero)
    proc = cli("export", "--from", zero, "--base-blend", "0.3", "--out", tmp_path / "never", check=False)
    assert proc.returncode != 0 and "base_blend 0, its base is OIDN itself" in proc.stderr
    # a base whose blend is not recorded cannot be moved: a one-line error naming the file, nothing written
    (zero / "model.json").write_text(json.dumps({k: v for k, v in record.items() if k != "base_blend"}))
    proc = cli("export", "--from", zero, "--base-blend", "0.3", "--out", tmp_path / "never", check=False)
    assert proc.returncode != 0 and "model.json: no base_blend" in proc.stderr and not (tmp_path / "never").exists()


@pytest.mark.slow
def test_export_puts_an_exported_model_on_another_base_and_keeps_its_control_module(tmp_path):
    """export --base FILE: the frozen base becomes FILE (its blend from the card beside it), the Control Module
    stays; a file of another OIDN network is refused with a one-line error naming it, nothing written."""
    from tests.helpers import cli

    out, base = _on_a_fine_tuned_base(tmp_path, 0.5)
    record = json.loads((out / "model.json").read_text())
    assert (out / "base.tza").read_bytes() == base.read_bytes() != (SHIPPED_MODEL / "base.tza").read_bytes()
    assert record["base_sha256"] == sha256(base) and record["base_blend"] == 0.5
    assert (out / "control.safetensors").read_bytes() == (SHIPPED_MODEL / "control.safetensors").read_bytes()
    assert f"--base {base}" in (out / "README.md").read_text()
    model, _ = tmodel.load(out)
    reference, _ = tmodel.load(SHIPPED_MODEL)
    buf = synthetic_buffers(24, 24, seed=2, noise=0.5)
    assert not np.array_equal(infer.Denoiser(model, record, "cpu").denoise(buf, spp=4),
                              infer.Denoiser(reference, record, "cpu").denoise(buf, spp=4))
    proc = cli("export", "--from", SHIPPED_MODEL, "--base", SHIPPED_MODEL / "oidn_ft" / "rt_hdr.tza",
               "--out", tmp_path / "never", check=False)
    assert proc.returncode != 0 and f"rt_hdr.tza: not OIDN's {record['base_network']}" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "never").exists()


@pytest.mark.parametrize("control_without_groups", [False, True])
def test_colour_albedo_normal_alone_get_the_base_alone_where_the_model_says_so(tmp_path, control_without_groups):
    """model.json control_without_groups false: an input with none of the Control Module's extra groups (an EXR
    from another renderer) gets the model's base alone, exactly the base_only row, and one more group (the
    variances) brings the Control Module back; true: the Control Module runs on colour, albedo and normal too."""
    model = tmp_path / "model"
    shutil.copytree(SHIPPED_MODEL, model)
    meta = json.loads((model / "model.json").read_text())
    (model / "model.json").write_text(json.dumps({**meta, "control_without_groups": control_without_groups}))
    den = load_denoiser(model, device="cpu")
    base = load_denoiser(model, device="cpu", base_only=True)
    full = synthetic_buffers(40, 32, seed=4, noise=0.6)
    plain = {k: full[k] for k in ("color", "albedo", "normal")}
    out = den.denoise(plain, spp=4)
    assert den.last_base_only is not control_without_groups and not den.last_estimate_only
    assert np.array_equal(out, base.denoise(plain, spp=4)) is not control_without_groups
    with_variance = {**plain, **{k: v for k, v in full.items() if k.endswith("variance")}}
    out_v = den.denoise(with_variance, spp=4)
    assert not den.last_base_only and den.model.control is not None
    assert not np.array_equal(out_v, base.denoise(with_variance, spp=4))
