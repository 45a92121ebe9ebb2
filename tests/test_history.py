"""The model reads the past: the history condition (the previous output warped into this frame, its
validity, ``has.history``), old models unchanged, the warm start from a model without it, and the packs."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from mcdenoise.pipeline import motion, schema, temporal
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.store import FrameKey
from mcdenoise.train import history as history_mod
from mcdenoise.train.data import Crops
from mcdenoise.train.history import SequenceInputs, previous_frames, with_history
from mcdenoise.train.infer import load_denoiser
from mcdenoise.train.model import (
    HISTORY_CHANNELS,
    SHIPPED_MODEL,
    ControlledOIDN,
    cond_names,
    inputs,
    load,
    reads_history,
    save,
    to_pu,
    widen_control,
)
from mcdenoise.train.sampler import Formulation

from .helpers import TINY, cli, look_at, train_tiny


def fixed_frame(seed: int = 3, size: tuple[int, int] = (24, 32)) -> dict[str, np.ndarray]:
    """Every schema buffer of a (24, 32) frame from a seeded generator: a fixed input for comparisons."""
    rng = np.random.default_rng(seed)
    H, W = size
    yy, xx = np.mgrid[0:H, 0:W] / max(H, W)
    truth = np.stack([0.5 + 0.4 * np.sin(6 * xx), 0.5 + 0.4 * np.cos(4 * yy), 0.3 + 0.2 * xx * yy], -1)
    out = {}
    for b in schema.BUFFERS:
        if b.name == "color":
            v = truth * rng.gamma(2.0, 0.5, truth.shape)
        elif b.radiance:
            v = 0.2 * truth * rng.gamma(2.0, 0.5, truth.shape)
        elif b.name == "normal":
            v = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (H, W, 3))
        elif b.name == "depth":
            v = 1.0 + truth[..., :1]
        else:
            v = np.clip(truth[..., :b.size] + 0.1 * rng.standard_normal((H, W, b.size)), 0, 1)
        out[b.name] = np.ascontiguousarray(v, dtype=np.float32)
        out[schema.variance_name(b.name)] = np.full(v.shape, 0.01, np.float32)
    return out


def shifted_history(frame: dict, valid_rows: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """A history for ``fixed_frame``: its colour × 0.9, valid on the first ``valid_rows`` rows only."""
    valid = np.zeros(frame["color"].shape[:2], bool)
    valid[:valid_rows] = True
    return frame["color"] * 0.9, valid


def test_a_model_without_history_keeps_its_condition_and_its_output_bit_for_bit():
    frame = fixed_frame()
    assert len(cond_names()) == 44 and not any(n.startswith(("history", "has.history")) for n in cond_names())
    den = load_denoiser(SHIPPED_MODEL, "cpu", precision="fp32")
    assert not den.history and not den.model.history
    # the condition the model was trained on, channel by channel (load refuses any other), and history
    # buffers in the input change nothing for a model without history: not its input, not its output
    assert den.meta["cond_channels"] == cond_names()
    np.testing.assert_array_equal(den.denoise(frame, spp=4, seed=0),
                                  den.denoise(with_history(frame, shifted_history(frame)), spp=4, seed=0))
    plain = inputs(frame, 4, clean_aux=False)
    given = inputs(with_history(frame, shifted_history(frame)), 4, clean_aux=False)
    for a, b in zip(plain, given):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(TrainError, match="does not read history"):
        den.denoise(frame, spp=4, history=shifted_history(frame))


def test_the_history_channels_are_the_warped_output_at_this_frames_exposure_and_the_flag():
    frame = fixed_frame()
    names = cond_names(True)
    assert names[-8:] == [*HISTORY_CHANNELS, "has.variance", "has.components", "has.materials", "has.history"]
    history = shifted_history(frame)
    x0, plain, scale = inputs(frame, 4)
    x, cond, s = inputs(with_history(frame, history), 4, history=True)
    _, alone, _ = inputs(frame, 4, history=True)
    assert s == scale and np.array_equal(x, x0) and cond.shape == (len(names), 32, 32)
    idx = [names.index(n) for n in HISTORY_CHANNELS]
    hist, valid = history
    expected = to_pu(torch.from_numpy(hist * scale)).numpy() * valid[..., None]
    np.testing.assert_array_equal(cond[idx[:3], :24, :32], np.moveaxis(expected, 2, 0))
    np.testing.assert_array_equal(cond[idx[3], :24, :32], valid.astype(np.float32))
    assert np.all(cond[names.index("has.history"), :24, :32] == 1)
    # the first frame (no history): history channels and flag zero, every other channel as without history
    assert not alone[idx + [names.index("has.history")]].any()
    others = [j for j, n in enumerate(names) if n not in (*HISTORY_CHANNELS, "has.history")]
    np.testing.assert_array_equal(alone[others], plain)
    np.testing.assert_array_equal(cond[others], plain)


def warm_started(folder: Path) -> Path:
    """train/shipped widened to read history (the history's weights zero), saved as a model folder."""
    shipped, meta = load(SHIPPED_MODEL)
    model = ControlledOIDN(shipped.base, len(cond_names(True)), history=True)
    model.control.load_state_dict(widen_control(shipped.control.state_dict(), model.control.layout,
                                                model.base.in_channels, cond_names(), cond_names(True)))
    blob = (SHIPPED_MODEL / meta["base"]).read_bytes()
    save(folder, model, blob, meta["base_what"], meta["base_network"], Formulation.from_record(meta["formulation"]),
         meta["spp"], {k: meta[k] for k in ("strength", "control_without_groups", "sigma")})
    return folder


def test_a_warm_start_from_a_model_without_history_begins_at_that_model(tmp_path):
    folder = warm_started(tmp_path / "temporal")
    record = json.loads((folder / "model.json").read_text())
    assert reads_history(record["cond_channels"]) and record["cond_channels"] == cond_names(True)
    temporal = load_denoiser(folder, "cpu", precision="fp32")
    shipped = load_denoiser(SHIPPED_MODEL, "cpu", precision="fp32")
    assert temporal.history and temporal.model.history
    frame = fixed_frame()
    reference = shipped.denoise(frame, spp=4, seed=0)
    # zero weights on the new columns: the history cannot move the output, and it is train/shipped's up to the
    # order of the first convolution's float32 sums, which changes with its width (measured: 1.6e-6 relative at
    # most, after the inverse PU transfer, whose slope grows with the radiance, amplified it; 1e-5 is that
    # round-off with margin, far below any learned effect)
    outputs = [temporal.denoise(frame, spp=4, seed=0, history=h)
               for h in (None, shifted_history(frame), shifted_history(frame, 24))]
    for out in outputs:
        np.testing.assert_allclose(out, reference, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(out, outputs[0], rtol=1e-6, atol=1e-7)


def test_widening_moves_each_column_to_its_name_and_zeroes_the_new_ones():
    layout_first = "enc_conv1a"
    old, new = ["a", "b"], ["a", "h", "b", "has.h"]
    w = torch.arange(2 * (1 + 2 + 3) * 9, dtype=torch.float32).reshape(2, 6, 3, 3)
    layout = type("L", (), {"first": layout_first})()
    out = widen_control({f"encoder.{layout_first}.weight": w, "other": torch.ones(1)}, layout, 1, old, new)
    wide = out[f"encoder.{layout_first}.weight"]
    assert wide.shape == (2, 8, 3, 3) and torch.equal(out["other"], torch.ones(1))
    for j_new, j_old in ((0, 0), (1, 1), (3, 2), (5, 3), (6, 4), (7, 5)):    # x.0, a, b, z.0..z.2
        assert torch.equal(wide[:, j_new], w[:, j_old])
    assert not wide[:, 2].any() and not wide[:, 4].any()                   # h, has.h


def test_previous_frames_pair_consecutive_frames_of_a_scene():
    keys = [FrameKey("a", 0), FrameKey("a", 1), FrameKey("a", 2), FrameKey("b", 0), FrameKey("c", 1)]
    assert previous_frames(keys) == {FrameKey("a", 1): FrameKey("a", 0), FrameKey("a", 2): FrameKey("a", 1)}


def test_a_still_camera_warps_the_previous_output_onto_itself():
    cam = motion.Camera(look_at([0, 0, -3], [0, 0, 0], [0, 1, 0]), 40.0, 32, 24)
    frame = fixed_frame()
    frame["depth"][:] = 3.0
    frame["depth"][:, :4] = 0.0                                    # background: no history there
    prev_out = np.random.default_rng(0).random((24, 32, 3)).astype(np.float32)
    warped, valid = motion.warp_previous(prev_out, motion.View.of(cam, frame), motion.View.of(cam, frame))
    assert valid.dtype == bool and not valid[:, :4].any() and valid[:, 4:].all()
    np.testing.assert_array_equal(warped[valid], prev_out[valid])   # pixel centres land on pixel centres
    assert not warped[~valid].any()


def synthetic_pack(frame: dict, history) -> dict[str, torch.Tensor]:
    x, cond, scale = inputs(with_history(frame, history), 4, history=True)
    target = np.pad(np.moveaxis(frame["color"], 2, 0), ((0, 0), (0, 8), (0, 0)))
    return {"x": torch.from_numpy(x)[None].half(), "cond": torch.from_numpy(cond)[None].half(),
            "scale": torch.tensor([scale]), "spp": torch.tensor([4], dtype=torch.int32),
            "frame": torch.tensor([0], dtype=torch.int32), "target": torch.from_numpy(target)[None].float()}


def test_history_crops_augment_it_as_a_colour_and_drop_it_whole():
    frame = fixed_frame()
    valid = np.ones((24, 32), bool)
    pack = synthetic_pack(frame, (frame["color"], valid))           # the history is this frame's colour
    names = cond_names(True)
    idx = [names.index(n) for n in HISTORY_CHANNELS]
    flag = names.index("has.history")
    keep, drop = (Crops(pack, 16, 8, seed=1, dropout=0.0, history_dropout=p) for p in (0.0, 1.0))
    for i in range(len(keep)):
        a, b = keep[i], drop[i]
        # flips, transposes and the colour permutation move the history with OIDN's colour input
        np.testing.assert_array_equal(a["cond"][idx[:3]].numpy(), a["x"][:3].numpy())
        # valid wherever the frame is (the padding to 32 rows is 0 in every channel, the flag's too)
        assert torch.equal(a["cond"][idx[3]], a["cond"][flag]) and a["cond"][flag].max() == 1
        assert not b["cond"][idx + [flag]].any()
        others = [j for j in range(len(names)) if j not in idx + [flag]]
        assert torch.equal(a["cond"][others], b["cond"][others]) and torch.equal(a["x"], b["x"])


def test_a_pack_without_history_has_no_history_group():
    frame = fixed_frame()
    x, cond, scale = inputs(frame, 4)
    pack = {"x": torch.from_numpy(x)[None].half(), "cond": torch.from_numpy(cond)[None].half(),
            "scale": torch.tensor([scale]), "spp": torch.tensor([4], dtype=torch.int32),
            "frame": torch.tensor([0], dtype=torch.int32), "target": torch.zeros(1, 3, 32, 32)}
    crops = Crops(pack, 16, 2, seed=0, history_dropout=1.0)
    assert not crops.history and set(crops.groups) == {"variance", "components", "materials"}
    assert crops[0]["cond"].shape[0] == len(cond_names())


# ---- the input a model that reads the past trains on (train.history.SequenceInputs) ---------------------


class _Frames:
    """A store's camera and frame records for a slanted plane seen by a camera sliding sideways: frame f of scene
    "a" rendered unless in ``missing``; ``read(f)`` its buffers (a fixed noisy frame of its own seed, depth of the
    plane)."""

    def __init__(self, missing=(), last=None):
        self.missing, self.last, self.reads = set(missing), last, []

    def frame_record(self, scene, frame):
        return None if frame in self.missing or (self.last is not None and frame > self.last) else {"frame": frame}

    def camera(self, scene, frame):
        return motion.Camera(look_at([0.05 * frame, 0, -3], [0.05 * frame, 0, 0], [0, 1, 0]), 40.0, 32, 24)

    def read(self, frame):
        self.reads.append(frame)
        buffers = fixed_frame(seed=10 + frame)
        buffers["depth"] = np.full((24, 32, 1), 3.0, np.float32)
        return buffers


@pytest.fixture
def cheap_oidn(monkeypatch):
    """OIDN's output replaced by a cheap function of the colour: the tests check what is fed where."""
    monkeypatch.setattr(history_mod, "oidn_output", lambda b: b["color"] * 0.5 + 0.1)


def expected(frames: _Frames, t: int, window: int, gate=None, first: int = 0):
    """Frame t's input averaged over the window and its history, built from temporal.InputWindow directly."""
    win, views, outs = temporal.InputWindow(window, gate=gate), {}, {}
    for f in range(first, t + 1):
        b = frames.read(f)
        views[f] = motion.View.of(frames.camera("a", f), b)
        outs[f] = win.take(b, views[f])
    hist = motion.warp_previous(outs[t - 1]["color"] * 0.5 + 0.1, views[t], views[t - 1]) if t - 1 >= first else None
    return outs[t], hist


@pytest.mark.parametrize("window", [1, 3])
def test_sequence_inputs_average_the_input_and_give_oidns_output_of_the_averaged_frame_before(cheap_oidn, window):
    frames = _Frames()
    walks = SequenceInputs(frames, window, gate=2.0)
    for t in (1, 2, 3):                             # consecutive frames: one walk
        got = walks.of(FrameKey("a", t), (0,), frames.read)
        avg, (warped, valid) = expected(_Frames(), t, window, 2.0)
        for k in avg:
            np.testing.assert_array_equal(got[k], avg[k], err_msg=k)
        np.testing.assert_array_equal(got["history"], warped)
        np.testing.assert_array_equal(got["history_valid"], valid.astype(np.float32))
        assert 0.5 < valid.mean() < 1                # the slide leaves a strip unseen
    # every frame read once: the walk continues from the frame before
    assert frames.reads == [0, 1, 2, 3]
    if window == 1:                                 # the frame's own input, as before averaging existed
        np.testing.assert_array_equal(got["color"], _Frames().read(3)["color"])
    else:                                           # the diffuse light of 3 frames: less than one frame's noise
        assert not np.array_equal(got["diffuse_indirect"], _Frames().read(3)["diffuse_indirect"])
        np.testing.assert_array_equal(got["specular_direct"], _Frames().read(3)["specular_direct"])


def test_sequence_inputs_average_the_frames_after_each_frame_as_the_window_does(cheap_oidn):
    """Frames 0-5 rendered (6 is not): frame t's input averages 2 frames before it and the 2 after it that are
    there, as ``InputWindow`` with those frames given ahead; each frame read once along the walk."""
    frames = _Frames(last=5)
    walks = SequenceInputs(frames, 3, gate=2.0, ahead=2)
    got = {t: walks.of(FrameKey("a", t), (0,), frames.read) for t in (1, 2, 3, 4, 5)}
    assert frames.reads == [0, 1, 2, 3, 4, 5]
    win, views, outs, clean = temporal.InputWindow(3, gate=2.0, ahead=2), {}, {}, _Frames()
    read = {f: clean.read(f) for f in range(6)}
    for f in range(6):
        views[f] = motion.View.of(clean.camera("a", f), read[f])
        ahead = [(win.keep(read[g]), motion.View.of(clean.camera("a", g), read[g])) for g in range(f + 1, min(f + 3, 6))]
        outs[f] = win.take(read[f], views[f], ahead)
    for t in (1, 2, 3, 4, 5):
        np.testing.assert_array_equal(got[t]["diffuse_direct"], outs[t]["diffuse_direct"])
        warped, _ = motion.warp_previous(outs[t - 1]["color"] * 0.5 + 0.1, views[t], views[t - 1])
        np.testing.assert_array_equal(got[t]["history"], warped)
    assert win.counts[-1] < win.counts[2]           # frame 5: nothing after it
    # frame 1 averages frame 0 and frames 2, 3: not its own input
    assert not np.array_equal(got[1]["diffuse_direct"], read[1]["diffuse_direct"])


def test_sequence_inputs_asked_out_of_order_start_the_window_over(cheap_oidn):
    frames = _Frames()
    walks = SequenceInputs(frames, 3)
    walks.of(FrameKey("a", 5), (0,), frames.read)
    assert frames.reads == [2, 3, 4, 5]              # frame 4's window (2-4), then 5
    got = walks.of(FrameKey("a", 2), (0,), frames.read)
    avg, (warped, _) = expected(_Frames(), 2, 3)
    np.testing.assert_array_equal(got["diffuse_direct"], avg["diffuse_direct"])
    np.testing.assert_array_equal(got["history"], warped)
    # another stack selection walks on its own
    walks.of(FrameKey("a", 3), (1,), frames.read)
    assert frames.reads[-3:] == [1, 2, 3]


def test_sequence_inputs_stop_at_a_frame_not_rendered(cheap_oidn):
    frames = _Frames(missing={1})
    walks = SequenceInputs(frames, 8)
    got = walks.of(FrameKey("a", 3), (0,), frames.read)
    assert frames.reads == [2, 3]                   # frame 0 is before the gap
    avg, (warped, _) = expected(_Frames(), 3, 8, first=2)
    np.testing.assert_array_equal(got["diffuse_indirect"], avg["diffuse_indirect"])
    np.testing.assert_array_equal(got["history"], warped)
    first = walks.of(FrameKey("a", 2), (0,), _Frames(missing={1}).read)
    assert "history" not in first                   # its frame before is not rendered: no history


# ---- on the tiny store: the history pack, a temporal run through the command line, its sequence --------


@pytest.fixture(scope="module")
def temporal_run(cleaned, tmp_path_factory):
    store, _ = cleaned
    runs = tmp_path_factory.mktemp("temporal") / "runs"
    proc = train_tiny("diffusion", store, runs, "diffusion.history=true", f"diffusion.init={SHIPPED_MODEL}",
                      "diffusion.epochs=1", "diffusion.val_frames=1", "diffusion.batch_size=2",
                      "diffusion.crops_per_frame=4", "diffusion.device=cpu", "diffusion.ema=0")
    return store, runs, proc


@pytest.mark.slow
def test_the_history_pack_holds_frames_after_the_first_with_their_warped_history(temporal_run):
    from safetensors import safe_open

    from mcdenoise.pipeline.store import Store
    store, runs, _ = temporal_run
    path = runs / "pack" / "train_oidn_base_calb_history.safetensors"
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata()
        cond = f.get_tensor("cond")
    frames = json.loads(meta["frames"])
    train = Store(store).frames_with("train")
    assert frames == [f"{k.scene}/{k.frame}" for k in train if k.frame >= 1] and frames
    assert json.loads(meta["cond"]) == cond_names(True) and meta["history"] == "oidn_prefilter, catmull_rom on x/(1+x)"
    assert meta["input"] == "diffuse light over 8 frames and 7 after, gate 2"   # eval.temporal_window, _ahead, _gate
    names = cond_names(True)
    assert cond.shape[1] == len(names) and torch.all(cond[:, names.index("has.history"), :24, :32] == 1)
    valid = cond[:, names.index("history.valid"), :24, :32].float()
    assert 0.5 < float(valid.mean()) <= 1.0                        # a small camera move: most pixels seen before
    assert cond[:, [names.index(n) for n in HISTORY_CHANNELS[:3]], :24, :32].float().amax() > 0


@pytest.mark.slow
def test_a_temporal_run_trains_and_denoise_sequence_feeds_it_its_own_history(temporal_run, tmp_path):
    from mcdenoise.pipeline.exr import read_header
    store, runs, proc = temporal_run
    run = runs / "diffusion_sppany"
    record = json.loads((run / "model.json").read_text())
    assert reads_history(record["cond_channels"]) and record["cond_channels"] == cond_names(True)
    scene = sorted(p.name for p in (Path(store) / "scenes").iterdir())[0]
    frames = str(Path(store) / "scenes" / scene / "###" / "s00.exr")
    out = cli("denoise", "--sequence", frames, "--spp", "4", "--device", "cpu",
              "--out", tmp_path / "out" / "f_###.exr", "--config", TINY, f"store={store}", f"runs={runs}")
    assert "reading its own warped previous output (learned history)" in out.stdout, out.stdout
    assert "history on 1 of 2 frames" in out.stdout, out.stdout
    records = [read_header(tmp_path / "out" / f"f_{n:03d}.exr") for n in range(2)]
    assert records[0]["temporal"] == {"learned": True, "history_fraction": None}
    assert records[1]["temporal"]["learned"] and records[1]["temporal"]["history_fraction"] > 0.5
    # the same command on a model without history: the per-frame model and the filter, as before
    out = cli("denoise", "--sequence", frames, "--spp", "4", "--device", "cpu",
              "--out", tmp_path / "old" / "f_###.exr")
    assert "ours + temporal filter on both sides, weight" in out.stdout and "train/shipped" in out.stdout, out.stdout


@pytest.mark.slow
def test_the_sequence_evaluation_runs_the_model_with_its_own_history_as_ours_temporal(temporal_run, tmp_path):
    from mcdenoise.evaluate.run import run_eval
    from mcdenoise.pipeline.config import load_config
    store, runs, _ = temporal_run
    cfg = load_config(TINY, [f"store={store}", f"runs={runs}", "eval.methods=[ours]", "eval.device=cpu",
                             "eval.sequence_methods=[ours, ours_filter, ours_temporal]", "eval.metrics=[l1, psnr]",
                             "eval.equal_time=none", "eval.spp=[4]", "eval.stress=false"])
    rows = run_eval(cfg, out=str(tmp_path / "report"), quiet=True)["sequences"]["test"]["spp"]["4"]["methods"]
    assert all(r["available"] for r in rows.values()), rows
    assert "diffusion_sppany" in rows["ours_temporal"]["checkpoint"]
    ours, learned, filtered = (rows[n]["per_frame"] for n in ("ours", "ours_temporal", "ours_filter"))
    for a, b, c in zip(ours, learned, filtered):
        if a["index"] == 0:     # no history yet: the model on the input averaged with the frames after; the filter
            # reads the frame after's output too (both sides), which the learned model does not
            assert b["metrics"] != a["metrics"] and c["metrics"] != b["metrics"]
        else:                                  # its own previous output, warped, changes what it makes
            assert b["metrics"]["psnr"] != a["metrics"]["psnr"] and "instability" in b["metrics"]
