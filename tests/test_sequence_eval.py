"""The evaluation along camera moves (``evaluate.sequence``) on the tiny config's rendered store: every scene's
frames in order, frame 1 apart, the temporal filter's history, the instability, and the page with its strip."""
import shutil

import numpy as np
import pytest
from PIL import Image

from mcdenoise.evaluate.methods import Method, MethodUnavailable, Noisy
from mcdenoise.evaluate.run import run_eval
from mcdenoise.evaluate.sequence import check_sequence_names, evaluate_sequences, load_sequence_methods, sequences
from mcdenoise.evaluate.sequence_report import write_sequence_page
from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.config import ConfigError, load_config
from mcdenoise.pipeline.schema import RADIANCE_COMPONENTS, beauty_from_components
from mcdenoise.pipeline.store import FrameKey, Store

from .helpers import TINY, look_at


@pytest.fixture(scope="module")
def report(cleaned, tmp_path_factory):
    store, runs = cleaned
    out = tmp_path_factory.mktemp("seq") / "report"
    cfg = load_config(TINY, [f"store={store}", f"runs={runs}", "eval.methods=[noisy, oidn_prefilter]",
                             "eval.sequence_methods=[noisy, oidn_prefilter, oidn_prefilter_temporal]",
                             "eval.metrics=[l1, psnr]", "eval.equal_time=none", "eval.spp=[4]"])
    return cfg, run_eval(cfg, out=str(out), quiet=True), out


@pytest.mark.slow
def test_every_test_scene_is_scored_frame_by_frame(report):
    cfg, result, out = report
    store = Store(cfg.store)
    test = [k for k in store.frames("test")]
    seq = result["sequences"]["test"]
    assert seq["scenes"] == {s: [str(k) for k in ks] for s, ks in sequences(test).items()} and seq["scenes"]
    rows = seq["spp"]["4"]["methods"]
    for name, row in rows.items():
        assert row["available"], name
        per_frame = row["per_frame"]
        assert [r["index"] for r in per_frame] == [i for ks in seq["scenes"].values() for i in range(len(ks))]
        for r in per_frame:                            # frame 1 has no frame before it: no instability
            assert ("instability" in r["metrics"]) == (r["index"] > 0)
            if r["index"] > 0:
                assert 0 <= r["metrics"]["instability"] < 1 and 0.5 < r["valid_fraction"] <= 1
    base, filtered = rows["oidn_prefilter"]["per_frame"], rows["oidn_prefilter_temporal"]["per_frame"]
    assert cfg.eval.temporal_ahead > 0
    for a, b in zip(base, filtered):                   # the history, and at t = 0 the frames after it, change it
        assert b["metrics"]["psnr"] != a["metrics"]["psnr"]
    # the noisy input flickers more than OIDN's output: fresh noise in every frame
    assert rows["noisy"]["mean"]["later"]["instability"] > 2 * rows["oidn_prefilter"]["mean"]["later"]["instability"]


@pytest.mark.slow
def test_the_page_its_curves_and_the_strip(report):
    _, result, out = report
    page = (out / "sequence.md").read_text()
    assert "| `oidn_prefilter_temporal` |" in page and "instability" in page
    # the page says how the temporal methods averaged their input: the tiny config's eval.temporal_* keys
    assert "(temporal methods: diffuse light over 8 frames and 7 after, gate 2, filter weight 0.7, on both sides)" in page
    assert "[sequence.md](sequence.md)" in (out / "eval.md").read_text()
    for name in ("sequence_test_psnr_spp4.png", "sequence_test_instability_spp4.png"):
        assert (out / name).stat().st_size > 0
    frames = len(next(iter(result["sequences"]["test"]["scenes"].values())))
    with Image.open(out / "sequence_test_spp4.gif") as gif:
        assert gif.n_frames == frames


@pytest.mark.slow
def test_the_camera_of_an_old_frame_comes_from_its_scene_description(report, tmp_path):
    cfg, _, _ = report
    root = tmp_path / "store"
    shutil.copytree(cfg.store, root)
    store = Store(root)
    key = FrameKey(sorted({k.scene for k in store.frames("test")})[0], 1)
    recorded = store.camera(key.scene, key.frame)
    record = store.frame_record(key.scene, key.frame)
    record.pop("fov_x", None)                           # a frame rendered before the fov was recorded
    store.write_frame_record(key.scene, key.frame, record)
    old = store.camera(key.scene, key.frame)
    fov = store.scene_manifest(key.scene)["description"]["camera"]["frames"][1]["fov"]
    assert old.fov_x == fov and np.array_equal(old.camera_to_world, recorded.camera_to_world)
    assert abs(recorded.fov_x - fov) < 1e-3            # the recorded fov is the described one (rounded to 1e-4)
    assert isinstance(old, motion.Camera)


def test_sequence_method_names_are_checked():
    check_sequence_names(["noisy", "oidn_prefilter", "oidn_prefilter_temporal", "ours", "ours_filter", "ours_temporal"])
    with pytest.raises(ConfigError, match="eval.sequence_methods: unknown method 'blur' .*ours_filter, ours_temporal"):
        check_sequence_names(["blur"])
    with pytest.raises(ConfigError, match="eval.sequence_methods: oidn_prefilter_temporal listed twice"):
        check_sequence_names(["oidn_prefilter_temporal", "oidn_prefilter_temporal"])


class _Model:
    """A loaded ``ours`` as the sequence evaluation sees it: its denoiser reads history or not."""
    def __init__(self, history: bool):
        self.denoiser, self.checkpoint = type("Den", (), {"history": history})(), "runs/x"


class _Loader:
    def __init__(self, history: bool):
        self.history = history

    def load(self, name, spp):
        return _Model(self.history)


def test_ours_temporal_is_the_model_reading_its_history_and_ours_filter_the_filter_on_ours():
    names = ["ours", "ours_filter", "ours_temporal"]
    methods, rows = load_sequence_methods(_Loader(False), names, 4)
    assert list(methods) == ["ours"] and rows["ours"]["available"] and rows["ours_filter"]["available"]
    assert rows["ours_filter"]["label"].endswith("+ temporal filter")
    assert load_sequence_methods(_Loader(False), names, 4, ahead=2)[1]["ours_filter"]["label"].endswith(
        "+ temporal filter on both sides")
    assert not rows["ours_temporal"]["available"] and "does not read history" in rows["ours_temporal"]["reason"]
    methods, rows = load_sequence_methods(_Loader(True), names, 4)
    assert all(r["available"] for r in rows.values())
    assert rows["ours_temporal"]["label"].endswith("reading its previous output")


def test_a_missing_frame_cuts_its_scene_into_two_runs():
    keys = [FrameKey("a", f) for f in (4, 0, 1, 3, 5)] + [FrameKey("b", 0), FrameKey("c", 2), FrameKey("c", 3)]
    assert sequences(keys) == {"a/000-001": [FrameKey("a", 0), FrameKey("a", 1)],
                               "a/003-005": [FrameKey("a", 3), FrameKey("a", 4), FrameKey("a", 5)],
                               "c": [FrameKey("c", 2), FrameKey("c", 3)]}


class _PlaneStore:
    """A store of one scene, a plane 3 units before a camera that slides sideways, frames ``frames`` only (the
    others missing): what the sequence loop reads of a store."""
    H, W = 12, 16

    def __init__(self, frames):
        self.frames = set(frames)

    def camera(self, scene, frame):
        assert frame in self.frames, frame
        return motion.Camera(look_at([0.05 * frame, 0, -3], [0.05 * frame, 0, 0], [0, 1, 0]), 40.0,
                             self.W, self.H)

    def geometry(self):
        return {"depth": np.full((self.H, self.W, 1), 3.0, np.float32),
                "normal": np.broadcast_to(np.float32([0, 0, -1]), (self.H, self.W, 3)).copy()}

    def read(self, scene, frame, spp, stacks):
        rng = np.random.default_rng(frame)
        return {"color": rng.gamma(2.0, 0.25, (self.H, self.W, 3)).astype(np.float32), **self.geometry()}

    def read_image(self, scene, frame, name, channels):
        return {"color": np.full((self.H, self.W, 3), 0.5, np.float32), **self.geometry()}, {}


class _Blur(Method):
    """A per-frame denoiser of the test: the frame's mean colour everywhere."""
    name = "oidn_prefilter"

    def denoise(self, buffers):
        return np.broadcast_to(buffers["color"].mean((0, 1)), buffers["color"].shape).astype(np.float32)


class _Bases:
    def load(self, name, spp):
        if name == "noisy":
            return Noisy()
        if name == "oidn_prefilter":
            return _Blur()
        raise MethodUnavailable(f"{name}: not in this test")


def test_runs_are_scored_apart_and_only_the_methods_asked_for_run(tmp_path):
    cfg = load_config(TINY, ["eval.metrics=[l1, psnr]",
                             "eval.sequence_methods=[noisy, oidn_prefilter, oidn_prefilter_temporal]"])
    store = _PlaneStore([0, 1, 3, 4])                       # frame 2 is missing
    keys = [FrameKey("a", f) for f in sorted(store.frames)]
    result, strips = evaluate_sequences(cfg, store, keys, lambda k: "gt_clean", [4], _Bases(), lambda k, spp: [0],
                                        ["l1", "psnr"])
    assert result["scenes"] == {"a/000-001": ["a/000", "a/001"], "a/003-004": ["a/003", "a/004"]}
    rows = result["spp"]["4"]["methods"]
    for name, row in rows.items():
        assert [r["index"] for r in row["per_frame"]] == [0, 1, 0, 1], name
        # frame 3 has no previous frame at hand: no instability against frame 1
        assert [("instability" in r["metrics"]) for r in row["per_frame"]] == [False, True, False, True], name
    # the filter's seconds are its base's and its own: reprojection, warp and blend
    base, filtered = rows["oidn_prefilter"]["per_frame"], rows["oidn_prefilter_temporal"]["per_frame"]
    assert all(b["seconds"] > a["seconds"] for a, b in zip(base, filtered) if a["index"] > 0)
    assert set(strips["4"]["outputs"]) == {"noisy", "oidn_prefilter", "oidn_prefilter_temporal"}
    # asked for the filter alone: its base runs (it filters its outputs), no other method
    cfg = load_config(TINY, ["eval.metrics=[l1, psnr]", "eval.sequence_methods=[oidn_prefilter_temporal]"])
    result, strips = evaluate_sequences(cfg, store, keys, lambda k: "gt_clean", [4], _Bases(), lambda k, spp: [0],
                                        ["l1", "psnr"])
    assert list(result["spp"]["4"]["methods"]) == ["oidn_prefilter_temporal"]
    assert set(strips["4"]["outputs"]) == {"oidn_prefilter", "oidn_prefilter_temporal"}


def test_a_run_without_sequences_leaves_no_sequence_page(tmp_path):
    (tmp_path / "sequence.md").write_text("# an earlier run's page\n")
    assert write_sequence_page({}, {}, tmp_path, 1000, 0) == ""
    assert not (tmp_path / "sequence.md").exists()


class _LitPlaneStore(_PlaneStore):
    """The plane with its light in components, as the store writes them."""

    def read(self, scene, frame, spp, stacks):
        rng = np.random.default_rng(frame)
        light = {n: rng.gamma(2.0, 0.05, (self.H, self.W, 3)).astype(np.float32) for n in RADIANCE_COMPONENTS}
        return {**light, "color": beauty_from_components(light), **self.geometry()}


@pytest.mark.parametrize("ahead", [0, 2])
def test_the_temporal_methods_denoise_the_input_averaged_over_the_window(ahead):
    cfg = load_config(TINY, ["eval.metrics=[l1, psnr]", "eval.sequence_methods=[oidn_prefilter, oidn_prefilter_temporal]",
                             "eval.temporal_window=3", "eval.temporal_weight=1", f"eval.temporal_ahead={ahead}"])
    store = _LitPlaneStore([0, 1, 2, 3])
    keys = [FrameKey("a", f) for f in range(4)]
    result, strips = evaluate_sequences(cfg, store, keys, lambda k: "gt_clean", [4], _Bases(), lambda k, spp: [0],
                                        ["l1", "psnr"])
    outputs = strips["4"]["outputs"]
    window = temporal.InputWindow(3, ahead=ahead)
    frames = [store.read("a", t, 4, [0]) for t in range(4)]
    views = [motion.View.of(store.camera("a", t), b) for t, b in enumerate(frames)]
    for t in range(4):
        later = [(window.keep(frames[u]), views[u]) for u in range(t + 1, min(t + 1 + ahead, 4))]
        np.testing.assert_array_equal(outputs["oidn_prefilter_temporal"][t],
                                      _Blur().denoise(window.take(frames[t], views[t], later)))
    # the first frame: its own input without frames after it, averaged with them otherwise
    assert np.array_equal(outputs["oidn_prefilter_temporal"][0], outputs["oidn_prefilter"][0]) == (ahead == 0)
    assert not np.array_equal(outputs["oidn_prefilter_temporal"][2], outputs["oidn_prefilter"][2])
    assert window.counts[-1] > 2.5                          # the plane slides a little: most pixels see 3 frames
    assert result["window"] == 3 and result["ahead"] == ahead
    assert ("and 2 after" in result["spp"]["4"]["methods"]["oidn_prefilter_temporal"]["label"]) == (ahead == 2)
    assert "on the diffuse light over 3 frames" in result["spp"]["4"]["methods"]["oidn_prefilter_temporal"]["label"]
