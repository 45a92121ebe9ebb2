"""The diffusion denoiser on OIDN: the network, data, sampler, training and inference (train/model.py,
data.py, sampler.py, train.py, infer.py)."""
import json
import shutil

import numpy as np
import pytest
import torch
from safetensors import safe_open

from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.errors import CheckpointError, ConfigError
from mcdenoise.pipeline.store import Store, sha256
from mcdenoise.pipeline.weights import save_safetensors
from mcdenoise.train import data, infer, model as tmodel, sampler
from mcdenoise.train.model import ControlledOIDN, load_unet, network_input
from mcdenoise.train.sampler import Formulation
from tests.helpers import TINY, cli, train_tiny

REFINE_TINY = ["diffusion.base_network=rt_hdr_alb_nrm", "diffusion.epochs=2", "diffusion.crop=16", "diffusion.batch_size=2",
               "diffusion.warmup_steps=1", "diffusion.lr=1e-3", "diffusion.device=cpu", "diffusion.val_frames=1"]
FORM = Formulation(estimate="oidn", residual_scale=0.02, steps=1)


@pytest.fixture(scope="module")
def base():
    torch.set_num_threads(1)
    return load_unet("rt_hdr_alb_nrm")


@pytest.fixture(scope="module", params=["rt_hdr_alb_nrm", "rt_hdr_calb_cnrm_large"])
def any_base(request):
    """OIDN's UNet and its large layout (the network of its prefiltered-aux mode at quality high)."""
    torch.set_num_threads(1)
    return load_unet(request.param)


def _random_inputs(n=2, side=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 9, side, side, generator=g) * 0.3
    cond = torch.rand(n, len(tmodel.cond_names()), side, side, generator=g)
    return x, cond


def test_the_untrained_controlled_model_is_oidn_exactly(any_base):
    base = any_base
    model = ControlledOIDN(base, len(tmodel.cond_names()))
    x, cond = _random_inputs()
    z = torch.randn(2, 3, 32, 32)
    out, est = model(x, cond, z, torch.tensor([999, 10]))
    assert torch.equal(out, est)
    assert torch.equal(est, base(x))
    # ... and so is every sampler: any steps, samples, start
    for steps, samples, start in ((1, 1, "estimate"), (3, 2, "estimate"), (2, 1, "noise"), (3, 1, "render")):
        mean, std, e = sampler.sample(model, x, cond, FORM, steps=steps, start=start, samples=samples, seed=4)
        assert torch.allclose(mean, e, atol=1e-6) and float(std.max()) < 1e-6


def test_the_control_module_gets_a_gradient_and_the_base_none(any_base):
    model = ControlledOIDN(any_base, len(tmodel.cond_names()))
    x, cond = _random_inputs()
    out, est = model(x, cond, torch.randn(2, 3, 32, 32), torch.tensor([999, 999]))
    (out - est - 0.01).abs().mean().backward()
    grads = [p.grad for p in model.trainable_parameters()]
    assert all(p.grad is None for p in model.base.parameters())
    assert sum(float(g.abs().sum()) for g in grads if g is not None) > 0
    # after one step away from zero the output depends on the condition and on z_t
    with torch.no_grad():
        for p in model.control.zero.parameters():
            p.add_(0.01 * torch.randn_like(p))
        model.control.encoder[model.control.layout.first].weight.add_(0.01)
    a = model(x, cond, torch.zeros(2, 3, 32, 32), torch.tensor([999, 999]))[0]
    b = model(x, cond * 0, torch.zeros(2, 3, 32, 32), torch.tensor([999, 999]))[0]
    c = model(x, cond, torch.ones(2, 3, 32, 32), torch.tensor([999, 999]))[0]
    assert not torch.allclose(a, b) and not torch.allclose(a, c)


def test_inputs_pad_like_oidn_and_mark_missing_groups():
    rng = np.random.default_rng(0)
    buffers = {"color": rng.random((21, 35, 3), dtype=np.float32), "albedo": rng.random((21, 35, 3), dtype=np.float32),
               "normal": rng.random((21, 35, 3), dtype=np.float32)}
    x, cond, scale = tmodel.inputs(buffers, 4)
    assert x.shape == (9, 32, 48) and cond.shape == (len(tmodel.cond_names()), 32, 48)
    ref = network_input(buffers["color"], buffers["albedo"], buffers["normal"], scale=scale)[0].numpy()
    np.testing.assert_array_equal(x, ref)
    names = tmodel.cond_names()
    for g in tmodel.groups():
        assert float(cond[names.index(f"has.{g}")].max()) == 0.0
    assert float(cond[names.index("spp"), 0, 0]) == pytest.approx(2 / 6)
    buffers["color.variance"] = np.ones((21, 35, 3), np.float32)   # a partial group counts as missing
    _, cond2, _ = tmodel.inputs(buffers, 4)
    np.testing.assert_array_equal(cond, cond2)
    with pytest.raises(Exception, match="needs normal"):
        tmodel.inputs({"color": buffers["color"], "albedo": buffers["albedo"]}, 4)


@pytest.fixture(scope="module")
def trained(cleaned, tmp_path_factory):
    store, runs = cleaned
    out = tmp_path_factory.mktemp("refine") / "runs"
    return store, out, train_tiny("diffusion", store, out, *REFINE_TINY)


@pytest.mark.slow
def test_training_starts_at_oidn_and_the_run_is_self_contained(trained, tmp_path):
    store, runs, proc = trained
    folder = runs / "diffusion_sppany"
    hist = json.loads((folder / "train.json").read_text())["history"]
    assert [h["epoch"] for h in hist] == [0, 1, 2]
    assert hist[0]["val"]["psnr"] == hist[0]["val"]["estimate_psnr"]
    assert all(np.isfinite(h["train_loss"]) for h in hist[1:])
    model, meta = tmodel.load(folder)
    assert meta["base_network"] == "rt_hdr_alb_nrm" and (folder / "base.tza").stat().st_size == 1841160
    # the evaluator's method and the denoise command run it
    from mcdenoise.evaluate.methods import Loader
    cfg = load_config(TINY, [f"store={store}", f"runs={runs}", *REFINE_TINY])
    method = Loader(cfg).load("ours_s3_k2", 4)
    key = Store(store).frames("val")[0]
    buf = Store(store).read(key.scene, key.frame, 4)
    hdr = method.denoise(buf)
    assert hdr.shape == buf["color"].shape and np.isfinite(hdr).all()
    assert method.uncertainty().shape == hdr.shape
    # σ's scale was fitted on the validation frames after training (no pixel has σ > 0 when the best
    # epoch is OIDN itself: then the scale stays 1)
    assert meta["sigma"]["steps"] == 3 and meta["sigma"]["samples"] == 4 and meta["sigma"]["scale"] > 0
    # the exported model folder is self-contained and gives the run's output (float16 weights)
    out = tmp_path / "shipped"
    cli("export", "--config", TINY, f"store={store}", f"runs={runs}", *REFINE_TINY, "--spp", "any", "--out", out)
    assert {p.name for p in out.iterdir()} == {"README.md", "base.tza", "control.safetensors", "model.json"}
    exported = infer.load_denoiser(out, "cpu")
    run = infer.load_denoiser(folder, "cpu")
    a, b = exported.denoise(buf, spp=4), run.denoise(buf, spp=4)
    assert np.abs(a - b).max() < 1e-2 * max(1.0, float(b.max()))
    # an input without albedo and normal gets OIDN on its colour, said so, not a crash
    rgb = exported.denoise({"color": buf["color"]}, spp=4)
    assert exported.last_estimate_only and exported.fallback == "OIDN rt_hdr" and rgb.shape == buf["color"].shape
    # a changed base is refused (the file is put back: the module's other tests read this run)
    intact = (folder / "base.tza").read_bytes()
    blob = bytearray(intact)
    blob[-1000] ^= 1
    (folder / "base.tza").write_bytes(bytes(blob))
    try:
        with pytest.raises(CheckpointError, match="base changed"):
            tmodel.load(folder)
    finally:
        (folder / "base.tza").write_bytes(intact)


@pytest.mark.slow
def test_a_warm_start_begins_at_the_trained_model(trained, tmp_path):
    """diffusion.init: the new run's epoch 0 is the given model (its base and Control Module), not OIDN."""
    store, runs, _ = trained
    folder = runs / "diffusion_sppany"
    _, meta = tmodel.load(folder)
    cli("train", "--model", "diffusion", "--spp", "any", "--config", TINY, f"store={store}", f"runs={tmp_path}",
        *REFINE_TINY, "diffusion.epochs=1", f"diffusion.init={folder}")
    hist = json.loads((tmp_path / "diffusion_sppany" / "train.json").read_text())["history"]
    assert hist[0]["val"]["psnr"] == pytest.approx(meta["metrics"]["psnr"], abs=1e-9)
    assert hist[0]["val"]["estimate_psnr"] == pytest.approx(meta["metrics"]["estimate_psnr"], abs=1e-9)
    warm = json.loads((tmp_path / "diffusion_sppany" / "model.json").read_text())
    assert warm["base_sha256"] == meta["base_sha256"] and warm["settings"]["init"] == str(folder)
    assert warm["settings"]["init_sha256"] == sha256(folder / "control.safetensors")
    # a start whose Control Module is not zero, under a config whose formulation differs from the model's (a warm
    # start from train/shipped with the default config's keys; 3 sampler steps, so the residual scale matters):
    # the run keeps the model's formulation and record, so its epoch 0 is still that model
    start = tmp_path / "start"
    shutil.copytree(folder, start)
    torch.manual_seed(0)
    with safe_open(str(start / "control.safetensors"), "pt") as f:
        moved = {k: f.get_tensor(k) + 0.05 * torch.randn_like(f.get_tensor(k)) for k in f.keys()}
        save_safetensors(start / "control.safetensors", moved, f.metadata())
    (start / "model.json").write_text(json.dumps({**meta, "control_without_groups": False}))
    epoch0 = {}
    for name, keys in {"same": [], "other": ["diffusion.residual_scale=0.5", "diffusion.steps=3",
                                             "diffusion.t_focus=0.1", "diffusion.train_steps=[9]"]}.items():
        proc = cli("train", "--model", "diffusion", "--spp", "any", "--config", TINY, f"store={store}",
                   f"runs={tmp_path / name}", *REFINE_TINY, "diffusion.epochs=1",
                   f"diffusion.init={start}", *keys)
        epoch0[name] = json.loads((tmp_path / name / "diffusion_sppany" / "train.json").read_text())["history"][0]
        assert ("diffusion.residual_scale=0.5" in proc.stdout) == bool(keys)
    assert epoch0["other"]["val"]["psnr"] == pytest.approx(epoch0["same"]["val"]["psnr"], abs=1e-9)
    assert epoch0["same"]["val"]["psnr"] != pytest.approx(meta["metrics"]["psnr"], abs=1e-3)   # the start moved
    warm = json.loads((tmp_path / "other" / "diffusion_sppany" / "model.json").read_text())
    assert warm["formulation"] == meta["formulation"]
    assert warm["settings"]["train_steps"] == meta["settings"]["train_steps"]
    assert warm["control_without_groups"] is False
    # a folder that is no trained model is a config error naming the key
    proc = cli("train", "--model", "diffusion", "--spp", "any", "--config", TINY, f"store={store}",
               f"runs={tmp_path / 'bad'}", *REFINE_TINY, f"diffusion.init={tmp_path / 'nothing'}", check=False)
    assert proc.returncode != 0 and "diffusion.init" in proc.stderr and not (tmp_path / "bad").exists()


def _first_frames(s: Store, split: str | None, scenes: int) -> list:
    """The first frame of each of the first ``scenes`` scenes of ``split``."""
    keys, seen = [], set()
    for key in s.frames(split):
        if key.scene not in seen and len(seen) < scenes:
            seen.add(key.scene)
            keys.append(key)
    return keys


@pytest.mark.slow
def test_pack_holds_each_frames_inputs_and_target(cleaned, tmp_path):
    """Every item of a pack (three scenes: three parts) is ``inputs`` of its frame's stacks at its spp, in frame
    order, and every target the frame's gt_clean, padded as the inputs are; the parts are gone."""
    from mcdenoise.pipeline.store import combine_stacks, stack_name
    store, _ = cleaned
    s = Store(store)
    keys = _first_frames(s, None, 3)
    assert len({k.scene for k in keys}) == 3
    path = data.build_pack(s, keys, tmp_path / "p.safetensors", quiet=True)
    pack = data.load_pack(path)
    assert not (tmp_path / "p.safetensors.parts").exists()
    row = 0
    for i, key in enumerate(keys):
        n, total, variants = data._frame_variants(s, key)
        for spp in sorted(variants):
            for v in range(variants[spp]):
                stacks = data.variant_stacks(spp, n, v, total)
                buffers = combine_stacks([s.read_image(key.scene, key.frame, stack_name(j))[0] for j in stacks], n)
                x, cond, scale = tmodel.inputs(buffers, spp)
                assert int(pack["frame"][row]) == i and int(pack["spp"][row]) == spp
                assert float(pack["scale"][row]) == pytest.approx(scale, rel=1e-6)
                assert torch.equal(pack["x"][row], torch.from_numpy(x.astype(np.float16)))
                assert torch.equal(pack["cond"][row], torch.from_numpy(cond.astype(np.float16)))
                row += 1
        gt = s.read_image(key.scene, key.frame, "gt_clean", ["color"])[0]["color"]
        h, w = gt.shape[:2]
        assert torch.equal(pack["target"][i, :, :h, :w], torch.from_numpy(np.moveaxis(gt, 2, 0).copy()))
        assert float(pack["target"][i, :, h:, :].abs().sum() + pack["target"][i, :, :, w:].abs().sum()) == 0.0
    assert row == len(pack["x"]) == len(pack["cond"]) and len(pack["target"]) == len(keys)


@pytest.mark.slow
def test_a_killed_pack_reuses_its_finished_scenes(cleaned, tmp_path):
    """The parts a killed build left are taken as they are where they hold what is asked (marked here), built
    again where they do not (a part of other frames), and the pack equals one built whole."""
    store, _ = cleaned
    s = Store(store)
    a, b = _first_frames(s, None, 2)
    whole = data.load_pack(data.build_pack(s, [a, b], tmp_path / "whole.safetensors", quiet=True))
    path = tmp_path / "p.safetensors"
    parts = tmp_path / "p.safetensors.parts"
    data._build_part(s, [a], parts / f"{a.scene}.safetensors", False, False, (1, None, 0))
    marked = data.load_pack(parts / f"{a.scene}.safetensors")
    marked["scale"] = marked["scale"] * 2
    save_safetensors(parts / f"{a.scene}.safetensors", marked, data._pack_meta(s, [a], False, False, (1, None, 0)))
    other = [k for k in s.frames() if k.scene == b.scene and k != b][:1] or [a]
    data._build_part(s, other, parts / f"{b.scene}.safetensors", False, False, (1, None, 0))
    pack = data.load_pack(data.build_pack(s, [a, b], path, quiet=True))
    rows_a = int((pack["frame"] == 0).sum())
    assert torch.equal(pack["scale"][:rows_a], whole["scale"][:rows_a] * 2)       # a's part, reused
    for name in ("x", "cond", "spp", "frame", "target"):
        assert torch.equal(pack[name], whole[name]), name                             # b's part, built again
    assert torch.equal(pack["scale"][rows_a:], whole["scale"][rows_a:])
    assert not parts.exists()


def test_pack_refuses_a_frame_of_another_size(tmp_path):
    """A pack is one size: a frame of another names itself and both sizes."""
    from mcdenoise.pipeline.exr import StoreError
    from mcdenoise.pipeline.store import FrameKey
    arrays: dict = {}
    a = FrameKey("s00000", 0)
    data._put(arrays, 0, 2, Store(tmp_path), a, x=np.ones((9, 16, 32), np.float32))
    assert arrays["x"].shape == (2, 9, 16, 32) and arrays["x"].dtype == np.float16 and arrays["x"][0].min() == 1
    b = FrameKey("s00001", 3)
    with pytest.raises(StoreError, match=f"frame {b} is 16×16, the pack's frames 32×16"):
        data._put(arrays, 1, 2, Store(tmp_path), b, x=np.ones((9, 16, 16), np.float32))


@pytest.mark.slow
def test_pack_items_are_augmented_consistently(cleaned, tmp_path):
    store, _ = cleaned
    s = Store(store)
    keys = s.frames("train")[:1]
    pack = data.load_pack(data.build_pack(s, keys, tmp_path / "p.safetensors", quiet=True))
    plain = data.Crops(pack, 16, 4, 0, augment=False, dropout=0.0)
    aug = data.Crops(pack, 16, 4, 0, augment=True, dropout=0.0)
    names = ["x.%d" % i for i in range(9)] + tmodel.cond_names()
    for i in range(4):
        a, b = plain[i], aug[i]
        full_a, full_b = torch.cat([a["x"], a["cond"]]), torch.cat([b["x"], b["cond"]])
        # same pixels, moved: the per-channel sums are a permutation within the colour triples
        assert torch.allclose(full_a.sum((1, 2)).sort().values, full_b.sum((1, 2)).sort().values, rtol=1e-4)
        # the target's colours moved as the input colour's and the albedo's did (the same crop, permuted)
        ta, tb = a["target"].double().sum((1, 2)), b["target"].double().sum((1, 2))
        perm = [int(torch.argmin((ta - v).abs())) for v in tb]
        assert sorted(perm) == [0, 1, 2] and torch.allclose(ta[perm], tb, rtol=1e-6)
        for key in ("color", "albedo", "diffuse_direct"):
            rgb = [names.index(f"{key}.{c}") for c in "RGB"]
            assert torch.allclose(full_a[rgb].double().sum((1, 2))[perm], full_b[rgb].double().sum((1, 2)), rtol=1e-5)
    dropped = data.Crops(pack, 16, 4, 0, augment=False, dropout=1.0)[0]
    names_c = tmodel.cond_names()
    assert all(float(dropped["cond"][names_c.index(f"has.{g}")].max()) == 0 for g in tmodel.groups())
    assert float(dropped["cond"][names_c.index("color.variance")].abs().max()) == 0
    assert float(dropped["cond"][names_c.index("color.R")].abs().max()) > 0


@pytest.mark.parametrize("strength", [1.0, 0.5])
def test_sigma_calibration_puts_half_the_errors_within_0_6745_sigma(base, strength):
    """A model whose samples differ: after the fit, the σ that ``denoise`` returns at the model's strength
    (the evaluator's ours_s3_k4 row) covers the median error exactly; strength scales the samples' spread
    and the mean's change, not the error, so the fit is made at that strength."""
    torch.manual_seed(0)
    model = ControlledOIDN(base, len(tmodel.cond_names()))
    with torch.no_grad():
        for p in model.control.parameters():
            p.add_(0.02 * torch.randn_like(p))
    meta = {"formulation": FORM.record(), "strength": strength}
    refiner = infer.Denoiser(model, meta, torch.device("cpu"))
    rng = np.random.default_rng(1)
    items, buffers = [], []
    for i in range(2):
        normal = rng.normal(size=(32, 32, 3))
        buf = {"color": rng.gamma(1.0, 0.4, (32, 32, 3)).astype(np.float32),
               "albedo": rng.random((32, 32, 3)).astype(np.float32),
               "normal": (normal / np.linalg.norm(normal, axis=2, keepdims=True)).astype(np.float32)}
        x, cond, scale = tmodel.inputs(buf, 4)
        items.append({"x": torch.from_numpy(x)[None], "cond": torch.from_numpy(cond)[None], "scale": scale,
                      "ref": buf["color"] * 0.5 + 0.1})
        buffers.append(buf)
    fit = infer.calibrate(refiner, items)
    assert fit["pixels"] > 1000 and fit["scale"] > 0 and fit["strength"] == strength
    refiner.sigma_scale = fit["scale"]
    ratios = []
    for buf, it in zip(buffers, items):
        hdr, s = refiner.denoise(buf, spp=4, steps=infer.SIGMA_STEPS, samples=infer.SIGMA_SAMPLES,
                                 with_std=True)
        e, s = np.abs(hdr - it["ref"]).mean(2).ravel(), s.mean(2).ravel()
        ratios.append(e[s > 0] / s[s > 0])
    assert np.median(np.concatenate(ratios)) == pytest.approx(0.6745, rel=1e-3)


@pytest.mark.slow
def test_extra_stores_add_their_train_frames_with_their_own_targets(cleaned, tmp_path):
    """diffusion.extra_stores: each store's train split is packed on its own (reused on the next run) and
    joined to the config's, every item keeping its own frame's target; a missing store names itself."""
    import shutil
    store, _ = cleaned
    other = tmp_path / "other"
    shutil.copytree(store, other)
    cfg = load_config(TINY, [f"store={store}", f"runs={tmp_path / 'runs'}", *REFINE_TINY,
                             f"diffusion.extra_stores=[{other}]"])
    one = data.StoreSource(load_config(TINY, [f"store={store}", f"runs={tmp_path / 'one'}", *REFINE_TINY])
                           ).train_pack(True)
    both = data.StoreSource(cfg).train_pack(True)
    n, frames = len(one["spp"]), len(one["target"])
    assert len(both["spp"]) == 2 * n and len(both["target"]) == 2 * frames
    extra = tmp_path / "runs" / "pack" / "train_extra0_oidn_base.safetensors"
    assert extra.exists()
    for i in range(n):
        assert int(both["frame"][n + i]) == int(one["frame"][i]) + frames
        assert torch.equal(both["target"][both["frame"][n + i]], one["target"][one["frame"][i]])
        assert torch.equal(both["x"][n + i], one["x"][i])
    stamp = extra.stat().st_mtime_ns
    data.StoreSource(cfg).train_pack(True)
    assert extra.stat().st_mtime_ns == stamp          # the same store's pack is reused, not rebuilt
    with pytest.raises(ConfigError, match="extra_stores.*nope.*no dataset"):
        load_config(TINY, [f"store={store}", *REFINE_TINY, f"diffusion.extra_stores=[{tmp_path / 'nope'}]"])


@pytest.mark.slow
def test_a_rank_that_does_not_build_waits_for_the_pack(cleaned, tmp_path, monkeypatch):
    """build=False (torchrun's ranks but 0) never writes: it waits until the pack another process builds is
    whole, then reads that one. (Two builds of one pack remove each other's parts.)"""
    store, _ = cleaned
    source = data.StoreSource(load_config(TINY, [f"store={store}", f"runs={tmp_path / 'runs'}", *REFINE_TINY]))
    path = source.pack_path("train")
    waits = []

    def rank0_builds(seconds):    # the other rank's build ends during the second wait
        assert not path.exists() and not path.with_name(path.name + ".parts").exists()
        waits.append(seconds)
        if len(waits) == 2:
            data.ensure_pack(source.store, source.train_keys, path, True, source.clean_aux, source.history,
                             source.window)

    monkeypatch.setattr(data.time, "sleep", rank0_builds)
    pack = source.train_pack(True, build=False)
    assert len(waits) == 2
    for name, tensor in data.load_pack(path).items():
        assert torch.equal(pack[name], tensor), name


@pytest.mark.slow
def test_the_time_budget_does_not_count_building_the_pack(cleaned, tmp_path, monkeypatch):
    """diffusion.time_budget_s counts the training, not the pack built before it (once for every run on the store):
    a pack that takes a million seconds here leaves a budget of a hundred thousand both epochs."""
    import time

    from mcdenoise.train import train as trainer
    store, _ = cleaned
    real_clock, real_load, late = time.perf_counter, trainer.load_data, [0.0]

    def slow_load(run):
        loaded = real_load(run)
        late[0] += 1e6
        return loaded

    monkeypatch.setattr(time, "perf_counter", lambda: real_clock() + late[0])
    monkeypatch.setattr(trainer, "load_data", slow_load)
    cfg = load_config(TINY, [f"store={store}", f"runs={tmp_path}", *REFINE_TINY, "diffusion.time_budget_s=1e5"])
    summary = trainer.train(cfg, "any", quiet=True)
    assert summary["trained_epochs"] == 2 and summary["seconds"] < 1e5


@pytest.mark.slow
def test_a_base_for_prefiltered_aux_reads_them_and_starts_at_oidns_final_frame_mode(cleaned, tmp_path):
    """diffusion.base_network=rt_hdr_calb_cnrm: the pack and every caller give the base albedo and normal
    prefiltered by OIDN's aux networks, so the untrained model (and the base alone) is OIDN's final-frame mode."""
    from mcdenoise.pipeline.metrics import psnr
    from mcdenoise.train import oidn
    store, _ = cleaned
    runs = tmp_path / "runs"
    cli("train", "--model", "diffusion", "--spp", "any", "--config", TINY, f"store={store}", f"runs={runs}",
        *REFINE_TINY, "diffusion.base_network=rt_hdr_calb_cnrm", "diffusion.epochs=1")
    folder = runs / "diffusion_sppany"
    hist = json.loads((folder / "train.json").read_text())["history"]
    assert hist[0]["val"]["psnr"] == hist[0]["val"]["estimate_psnr"]
    meta = json.loads((folder / "model.json").read_text())
    assert meta["base_network"] == "rt_hdr_calb_cnrm"
    with safe_open(str(runs / "pack" / "train_oidn_base_calb.safetensors"), framework="pt") as f:
        assert f.metadata()["aux"] == "prefiltered"
    assert not (runs / "pack" / "train_oidn_base.safetensors").exists()
    key = Store(store).frames("val")[0]
    buf = Store(store).read(key.scene, key.frame, 4)
    base_only = infer.load_denoiser(folder, "cpu", base_only=True)
    assert base_only.clean_aux
    # OIDN in its final-frame mode running this network (at quality high its own choice is the large one)
    blob = (folder / "base.tza").read_bytes()
    out = base_only.denoise(buf, spp=4)
    assert psnr(out, oidn.denoise(buf, weights=blob, clean_aux=True)) > 80
    # the same network on the aux as rendered is another output: the prefilter is what makes them equal
    assert psnr(out, oidn.denoise(buf, weights=blob)) < 60


def test_the_base_network_is_one_oidn_has_for_colour_albedo_and_normal():
    assert load_config(None, ["diffusion.base_network=rt_hdr_calb_cnrm_large"]).diffusion.base_network \
        == "rt_hdr_calb_cnrm_large"
    for wrong in ("rt_hdr", "rt_hdr_alb", "rt_ldr_calb_cnrm"):
        with pytest.raises(ConfigError, match="diffusion.base_network"):
            load_config(None, [f"diffusion.base_network={wrong}"])


@pytest.mark.slow
def test_strength_moves_the_output_from_the_base_to_the_trained_model(trained, tmp_path, monkeypatch):
    """strength k: the base's output plus k times what the Control Module changes, in OIDN's output space, so
    0 is the base alone and every pixel of k = 0.5 lies between the base's and the full model's (the inverse
    transfer is monotone); the evaluator's strengthN, denoise --strength and export --strength give that."""
    from mcdenoise.evaluate.methods import Loader, parse
    from mcdenoise.pipeline.exr import read_image

    store, runs, _ = trained
    # a Control Module that changes OIDN's output clearly (two tiny epochs barely move it)
    moved = tmp_path / "runs" / "diffusion_sppany"
    shutil.copytree(runs / "diffusion_sppany", moved)
    torch.manual_seed(1)
    with safe_open(str(moved / "control.safetensors"), "pt") as f:
        state = {k: f.get_tensor(k) + 0.02 * torch.randn_like(f.get_tensor(k)) for k in f.keys()}
        save_safetensors(moved / "control.safetensors", state, f.metadata())
    key = Store(store).frames("val")[0]
    buf = Store(store).read(key.scene, key.frame, 4)
    den = infer.load_denoiser(moved, "cpu")
    full = den.denoise(buf, spp=4, strength=1.0)
    assert den.last_clamped == 0      # (a clamped pixel is the same at every strength that reaches the clamp)
    half = den.denoise(buf, spp=4, strength=0.5)
    # strength 0 hands the base's own estimate of this very run to the inverse transfer: compared bit for
    # bit with that estimate through the same transfer (the base-only refiner reaches the same image by
    # another float32 path, the sampler's steps on a zero change, and differs from it by round-off)
    seen = {}
    real_sample, real_to_hdr = infer.sample, infer.Denoiser.to_hdr
    monkeypatch.setattr(infer, "sample", lambda *a, **k: seen.setdefault("sample", real_sample(*a, **k)))
    monkeypatch.setattr(infer.Denoiser, "to_hdr",
                        staticmethod(lambda mean, std, scale, H, W: seen.setdefault("to_hdr", (mean, scale, H, W))
                                     and real_to_hdr(mean, std, scale, H, W)))
    none = den.denoise(buf, spp=4, strength=0.0)
    monkeypatch.undo()
    est = seen["sample"][2]
    mean, scale, H, W = seen["to_hdr"]
    assert torch.equal(mean, est.clamp(max=1.0))
    base = real_to_hdr(est.clamp(max=1.0), torch.zeros_like(est), scale, H, W)[0]
    np.testing.assert_array_equal(none, base)
    assert np.abs(full - base).max() > 0.05 * float(base.max())
    # k = 0.5 is est + 0.5 (mean - est) in OIDN's space, rounded to float32 (2^-24 of values <= 1), then
    # through the monotone inverse transfer, whose float32 evaluation adds a few ulps (2^-23 relative
    # each): the margin 1e-5 relative is about 80 float32 ulps, far above that, far below any real step
    lo, hi = np.minimum(base, full), np.maximum(base, full)
    assert np.all(half >= lo - 1e-5 * (1 + hi)) and np.all(half <= hi + 1e-5 * (1 + hi))
    apart = np.abs(full - base) > 0.01 * (1 + hi)
    assert apart.mean() > 0.1 and np.all(np.abs(half - base)[apart] > 0) and np.all(np.abs(half - full)[apart] > 0)
    assert np.array_equal(den.denoise(buf, spp=4), full)         # the model's own strength: 1 unless set

    # the evaluator's token
    assert parse("ours_large2_strength50").strength == 0.5 and parse("ours_large2_strength50").variant == "large2"
    with pytest.raises(ConfigError, match="strength150"):
        parse("ours_strength150")
    cfg = load_config(TINY, [f"store={store}", f"runs={tmp_path / 'runs'}", *REFINE_TINY])
    np.testing.assert_array_equal(Loader(cfg).load("ours_strength50", 4).denoise(buf), half)
    # export --strength writes it into a copy of an exported model: that copy applies it by default
    exported, out = tmp_path / "exported", tmp_path / "half"
    cli("export", "--config", TINY, f"store={store}", f"runs={tmp_path / 'runs'}", *REFINE_TINY, "--spp", "any",
        "--out", exported)
    proc = cli("export", "--from", exported, "--strength", "0.5", "--out", out)
    assert json.loads((out / "model.json").read_text())["strength"] == 0.5
    assert "--strength 0.5" in (out / "README.md").read_text()
    # σ was fitted at strength 1 by the run: the export says so, and --fit-sigma fits it again at 0.5
    assert json.loads((exported / "model.json").read_text())["sigma"].get("strength", 1.0) == 1.0
    assert "σ's scale was fitted at strength 1" in proc.stdout and "--fit-sigma" in (out / "README.md").read_text()
    refit = tmp_path / "refit"
    cli("export", "--from", out, "--fit-sigma", "--out", refit, "--config", TINY, f"store={store}", *REFINE_TINY)
    sigma = json.loads((refit / "model.json").read_text())["sigma"]
    assert sigma["strength"] == 0.5 and sigma["frames"] == 1 and sigma["store"] == str(store)
    assert sigma["scale"] != json.loads((out / "model.json").read_text())["sigma"]["scale"]
    assert (refit / "control.safetensors").read_bytes() == (out / "control.safetensors").read_bytes()
    assert "## σ fitted again" in (refit / "README.md").read_text()
    proc = cli("export", "--from", out, "--fit-sigma", "--out", tmp_path / "none", "--config", TINY, f"store={store}",
               *REFINE_TINY, "diffusion.val_frames=0", check=False)
    assert proc.returncode != 0 and "val_frames" in proc.stderr and not (tmp_path / "none").exists()
    assert "strength" not in json.loads((exported / "model.json").read_text())
    np.testing.assert_array_equal(infer.load_denoiser(out, "cpu").denoise(buf, spp=4),
                                  infer.load_denoiser(exported, "cpu").denoise(buf, spp=4, strength=0.5))
    # ... and denoise --strength on the command line
    cli("denoise", "--config", TINY, f"store={store}", f"runs={tmp_path / 'runs'}", *REFINE_TINY, "--spp", "4",
        "--frame", f"{key.scene}/{key.frame:03d}", "--out", tmp_path / "half.exr", "--strength", "0.5", "--seed", "0")
    image, record = read_image(tmp_path / "half.exr")
    assert record["strength"] == 0.5
    np.testing.assert_allclose(image["color"], half, rtol=1e-6, atol=1e-6)
    # outside [0, 1]: one line naming the flag, nothing written
    proc = cli("export", "--from", moved, "--strength", "1.5", "--out", tmp_path / "bad", check=False)
    assert proc.returncode != 0 and "--strength" in proc.stderr and not (tmp_path / "bad").exists()


def test_precision_changes_the_networks_arithmetic_only():
    """fp32 (the CPU's default) is the model as trained, bit for bit; bf16 autocast (8 mantissa bits, about 48 dB
    per rounding, accumulated over the networks' layers) stays within 30 dB of it but is not it; an unknown
    precision is one clean error."""
    from mcdenoise.pipeline.errors import TrainError
    from mcdenoise.train.bench import synthetic_frame

    buf = synthetic_frame(32, 48)
    default = infer.load_denoiser(tmodel.SHIPPED_MODEL, "cpu")
    assert default.precision == "fp32"
    fp32 = default.denoise(buf, spp=4)
    assert np.array_equal(fp32, infer.load_denoiser(tmodel.SHIPPED_MODEL, "cpu", precision="fp32").denoise(buf, spp=4))
    bf16 = infer.load_denoiser(tmodel.SHIPPED_MODEL, "cpu", precision="bf16").denoise(buf, spp=4)
    tm = lambda x: x / (1 + x)  # noqa: E731
    mse = float(np.mean((tm(bf16).astype(np.float64) - tm(fp32)) ** 2))
    assert bf16.dtype == np.float32 and 0 < mse and 10 * np.log10(1 / mse) > 30
    with pytest.raises(TrainError, match="precision 'fp8'"):
        infer.load_denoiser(tmodel.SHIPPED_MODEL, "cpu", precision="fp8")


def test_channels_last_tensors_give_the_same_output(base):
    """bench-denoise times the networks on NHWC tensors too: the same computation in another memory layout
    (convolutions sum in another order: equal to float32 rounding, not bit for bit)."""
    model = ControlledOIDN(base, len(tmodel.cond_names()))
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for p in model.control.parameters():      # a trained-like Control Module: its zero convolutions not zero
            p.add_(0.05 * torch.randn(p.shape, generator=g))
    x, cond = _random_inputs(n=1)
    mean, _, est = sampler.sample(model, x, cond, FORM, steps=2)
    assert float((mean - est).abs().max()) > 1e-3               # the Control Module changes the output
    model.to(memory_format=torch.channels_last)
    nhwc = [t.contiguous(memory_format=torch.channels_last) for t in (x, cond)]
    mean_l, _, est_l = sampler.sample(model, *nhwc, FORM, steps=2)
    assert torch.allclose(mean_l, mean, atol=2e-5, rtol=1e-4) and torch.allclose(est_l, est, atol=2e-5, rtol=1e-4)


def test_the_sampler_does_no_work_twice(base):
    """Its arithmetic: the base's encoder once, its decoder for the estimate, then per step the Control Module
    and the decoder again; the base alone is one encoder and one decoder."""
    from torch.utils.flop_counter import FlopCounterMode

    from mcdenoise.train.bench import network_gflops

    model = ControlledOIDN(base, len(tmodel.cond_names()))
    x, cond = _random_inputs(n=1)
    z, t = torch.zeros(1, 3, 32, 32), torch.tensor([999])

    def gflop_per_mpix(fn):
        with FlopCounterMode(display=False) as counter, torch.no_grad():
            fn()
        return counter.get_total_flops() / 1e9 / (32 * 32 / 1e6)
    feats = base.encode(x)
    enc, dec = gflop_per_mpix(lambda: base.encode(x)), gflop_per_mpix(lambda: base.decode(feats))
    ctl = gflop_per_mpix(lambda: model.control(torch.cat([x, cond, z], 1), t))
    for steps in (1, 3):
        g = network_gflops(model, FORM, steps, side=32)
        assert g["base"] == pytest.approx(enc + dec, abs=0.01)
        assert g["ours"] == pytest.approx(enc + dec + steps * (ctl + dec), abs=0.01)
    model.control = None
    g = network_gflops(model, FORM, 1, side=32)
    assert g["ours"] == g["base"]


def test_an_epoch_without_a_full_batch_is_a_config_error_naming_the_keys():
    from mcdenoise.train.train import check_steps

    check_steps(8, 8, 2, 4)                               # one full batch: one step
    with pytest.raises(ConfigError, match=r"diffusion\.batch_size 8: more than the 7 training crops .*"
                                          r"diffusion\.batch_size=7 or raise diffusion\.crops_per_frame"):
        check_steps(7, 8, 7, 1)


@pytest.mark.slow
def test_a_run_that_would_take_no_step_stops_before_any_work_in_one_line(cleaned, tmp_path):
    store, _ = cleaned
    proc = cli("train", "--model", "diffusion", "--spp", "any", "--config", TINY, f"store={store}",
               f"runs={tmp_path / 'runs'}", *REFINE_TINY, "diffusion.batch_size=64", check=False)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert proc.stderr.startswith("error: diffusion.batch_size 64: more than the") and "no optimiser step" in proc.stderr
    assert not (tmp_path / "runs" / "pack").exists()       # refused before the store was decoded


def test_an_implausible_sigma_fit_is_reported_as_a_failure_and_not_stored(tmp_path, monkeypatch, capsys):
    """σ's scale is the error over the samples' spread; 3e5 says the spread does not track the error on these
    frames: the run says the fit failed and model.json keeps no σ (a plausible fit is stored as before)."""
    from types import SimpleNamespace

    from mcdenoise.train import train as trainer

    run = SimpleNamespace(rank=0, folder=tmp_path, device="cpu", cfg=SimpleNamespace(seed=0), name="r", says=True)
    for scale, stored in ((3.36e5, False), (2.8, True)):
        (tmp_path / "model.json").write_text(json.dumps({"format": "x", "sigma": {"scale": 9.0}}))
        fit = {"scale": scale, "steps": 3, "samples": 4, "pixels": 100, "strength": 1.0}
        monkeypatch.setattr(infer, "load_denoiser", lambda folder, device: None)
        monkeypatch.setattr(infer, "calibrate", lambda den, val, seed, fit=fit: fit)
        trainer.calibrate_sigma(run, [{"frame": 0}])
        record = json.loads((tmp_path / "model.json").read_text())
        out = capsys.readouterr().out
        assert (record.get("sigma") == fit) == stored and ("σ fit failed" in out) != stored
