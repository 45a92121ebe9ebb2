"""The evaluation stage end to end: a synthetic store written with the store API (no rendering),
an untrained Isik checkpoint, a stand-in for the diffusion model's ``train.infer``, and through the
command line the errors users meet and an external Mitsuba scene (rendered).

The store: one test scene with FRAMES frames of W×H pixels; GT_clean is a noise-free smooth
pattern, GT1/GT2 (64 spp) and four 4-spp stacks are that pattern with multiplicative Gaussian
noise of standard deviation 0.7·sqrt(4/spp), so pooling k stacks behaves like k times the
samples; the per-image render seconds follow t(N) = A + B·N exactly.
"""
import csv
import json
import math
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.evaluate.run import frame_groups, run_eval
from mcdenoise.evaluate.stability import synthetic_buffers
from mcdenoise.pipeline import schema
from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.store import Store, image_names
from tests.helpers import save_untrained_isik

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.yaml"
H, W = 24, 32
FRAMES = 2
STACKS = 4
GT_SPP = 64
A, B = 0.01, 0.001
SCENE = "s00001"
FAKE_DENOISE_SECONDS = 0.05


def make_store(root: Path, scenes: dict[str, str] | None = None, frames: int = FRAMES) -> Path:
    """``scenes``: scene id → split (default: SCENE in the test split); every scene as described above."""
    scenes = scenes or {SCENE: "test"}
    store = Store(root)
    names = image_names(STACKS)
    splits = {"train": [], "val": [], "test": []}
    for scene, split in scenes.items():
        splits.setdefault(split, []).append(scene)
    store.write_manifest({"config": {}, "scenes": list(scenes), "splits": splits, "images": names, "packages": {}})
    for i, (scene, split) in enumerate(scenes.items()):
        store.write_scene_manifest(scene, {"scene": scene, "index": i + 1, "split": split, "frames": frames,
                                           "resolution": [W, H], "gt_spp": GT_SPP, "stack_spp": 4, "stacks": STACKS,
                                           "images": names})
        for f in range(frames):
            _write_frame(store, scene, f, 0.9 * f + 0.37 * i, 100 * f + 1000 * i, names)
    return root


def _write_frame(store: Store, scene: str, f: int, phase: float, seed: int, names: list[str]) -> None:
    records = {}
    for k, name in enumerate(names):
        spp = GT_SPP if name.startswith("gt") else 4
        buf = synthetic_buffers(H, W, seed=seed + k, noise=0.7 * math.sqrt(4 / spp), spp=spp, phase=phase)
        records[name] = store.write_image(scene, f, name, buf, meta={
            "image": name, "scene": scene, "frame": f, "spp": spp, "render_seconds": A + B * spp})
    clean = synthetic_buffers(H, W, noise=0.0, phase=phase)["color"]
    store.write_image(scene, f, "gt_clean", {"color": clean, schema.variance_name("color"): np.zeros_like(clean)},
                      meta={"image": "gt_clean", "scene": scene, "frame": f, "source": "gt1"})
    store.write_frame_record(scene, f, {"scene": scene, "frame": f, "width": W, "height": H, "images": records})


class FakeDiffusion:
    """Stands in for train.infer's denoiser: a 3×3 box blur (base_only: the input, brightened)."""

    calls: list = []

    def __init__(self, folder, device, base_only):
        from mcdenoise.train.sampler import Formulation
        self.folder, self.device, self.base_only = Path(folder), device, base_only
        self.formulation, self.meta = Formulation(steps=27), {"base_what": "a box blur"}

    def denoise(self, buffers, spp, skip, seed, steps=None, start=None, samples=1, with_std=False, strength=None,
                history=None):
        FakeDiffusion.calls.append({"spp": spp, "skip": skip, "seed": seed, "base_only": self.base_only,
                                    "start": start, "keys": sorted(buffers)})
        time.sleep(FAKE_DENOISE_SECONDS * (27 - (skip or 0)) / 27)
        c = buffers["color"]
        if self.base_only:
            out = c * 1.5
        else:
            p = np.pad(c, ((1, 1), (1, 1), (0, 0)), mode="edge")
            out = sum(p[i:i + c.shape[0], j:j + c.shape[1]] for i in range(3) for j in range(3)) / 9
        return (out, np.zeros_like(out)) if with_std else out


def fake_infer_module() -> types.ModuleType:
    mod = types.ModuleType("mcdenoise.train.infer")

    def run_dir(cfg, spp):
        return Path(cfg.runs) / f"diffusion_spp{spp}"

    def load_denoiser(folder, device="cpu", base_only=False):
        if not Path(folder).exists():
            raise FileNotFoundError(f"{folder}: no checkpoint")
        return FakeDiffusion(folder, device, base_only)

    mod.run_dir, mod.load_denoiser = run_dir, load_denoiser
    return mod


@pytest.fixture(scope="module")
def store_root(tmp_path_factory):
    return make_store(tmp_path_factory.mktemp("eval") / "store")


def cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "pipeline", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


@pytest.mark.slow
def test_eval_end_to_end(store_root, tmp_path, monkeypatch):
    runs = tmp_path / "runs"
    save_untrained_isik(runs / "isik_spp4")
    (runs / "diffusion_spp4").mkdir(parents=True)            # ours has a checkpoint at 4 spp only
    (runs / "diffusion_spp4" / "model.json").write_text("{}")
    monkeypatch.setitem(sys.modules, "mcdenoise.train.infer", fake_infer_module())
    FakeDiffusion.calls.clear()
    methods = ["noisy", "oidn", "oidn_color", "isik", "ours", "ours_skip18", "base_only", "ours_render_skip18"]
    cfg = load_config(TINY, [f"store={store_root}", f"runs={runs}", f"eval.methods={json.dumps(methods)}",
                             "eval.equal_time=pool", "eval.equal_time_methods=[ours, oidn, isik]", "eval.device=cpu",
                             "eval.seed=5", "diffusion.shipped=false"])   # no fallback to train/shipped
    out = tmp_path / "report"
    result = run_eval(cfg, spps=[4, 16, 64], out=str(out), quiet=True)

    for name in ("eval.md", "eval.json", "eval_test_spp4.csv", "eval_test_spp16.csv", "error_vs_time_test.png",
                 "crops_test_spp4.png", "crops_test_spp16.png"):
        assert (out / name).stat().st_size > 0, name
    g = result["groups"]["test"]
    assert g["frames"] == [f"{SCENE}/000", f"{SCENE}/001"] and set(g["reference"].values()) == {"gt_clean"}
    # frames written without a camera: no sequence page for them, and the reason names the record
    skipped = result["sequences"]["test"]["skipped"]
    assert "frame.json" in skipped and "no camera" in skipped
    assert "4 stacks of 4 spp" in g["spp"]["64"]["skipped"]
    # render-time model recovered from frame.json
    assert all(c["how"] == "fit" and c["b"] == pytest.approx(B) and c["a"] == pytest.approx(A)
               for c in g["render_cost"].values())
    # MC curve: pooled stacks 1, 2, 4 (4, 8, 16 spp) and GT2 at 64 spp; error falls with samples
    mean = g["mc_mean"]
    assert [p["spp"] for p in mean] == [4, 8, 16, 64]
    assert all(a["l1"] > b["l1"] and a["psnr"] < b["psnr"] for a, b in zip(mean, mean[1:]))
    assert mean[2]["seconds"] == pytest.approx(A + B * 16)

    e4, e16 = g["spp"]["4"], g["spp"]["16"]
    rows = e4["methods"]
    # the noisy row is the MC curve's first point, and it is worth exactly 4 spp
    assert rows["noisy"]["metrics"]["l1"] == pytest.approx(mean[0]["l1"], rel=1e-6)
    noisy_pt = next(p for p in e4["time_vs_error"] if p["method"] == "noisy")
    assert noisy_pt["spp_equivalent_l1"][0] == pytest.approx(4) and noisy_pt["spp_equivalent_l1"][1] == "interpolated"
    assert noisy_pt["spp_equivalent_psnr"][0] == pytest.approx(4)
    # real denoisers beat the noisy input
    assert rows["oidn"]["metrics"]["l1"] < 0.5 * rows["noisy"]["metrics"]["l1"]
    assert rows["oidn"]["metrics"]["psnr"] > rows["noisy"]["metrics"]["psnr"] + 5
    assert rows["isik"]["available"] and rows["isik"]["failed_frames"] == 0
    assert set(rows["noisy"]["metrics"]) == {"l1", "psnr", "ssim", "flip", "hdr_flip", "fvvdp"}
    # at 16 spp: no Isik or diffusion checkpoint -> rows with the reason, no numbers
    assert not e16["methods"]["isik"]["available"]
    assert "make train MODEL=isik SPP=16" in e16["methods"]["isik"]["reason"]
    assert not e16["methods"]["ours"]["available"] and "diffusion_spp16" in e16["methods"]["ours"]["reason"]
    assert "metrics" not in e16["methods"]["ours"]

    # ours plugged in through train.infer: spp, skip, seed, base_only and the start reach the denoiser
    # (None: the run's own setting)
    seen = {(c["spp"], c["skip"], c["base_only"], c["seed"], c["start"]) for c in FakeDiffusion.calls}
    assert seen == {(4, None, False, 5, None), (4, 18, False, 5, None), (4, None, True, 5, None),
                    (4, 18, False, 5, "render")}
    assert "from the render" in (out / "eval.md").read_text()
    # every row names the weights it ran, in the table's weights column: the run folder for ours
    md_rows = {}                                              # the first table: 4 spp
    for line in (out / "eval.md").read_text().splitlines():
        if line.startswith("| ") and "(`" in line:
            md_rows.setdefault(line.split("(`")[1].split("`)")[0], line.split(" | "))
    header = next(line for line in (out / "eval.md").read_text().splitlines() if line.startswith("| method"))
    col = header.split(" | ").index("weights")
    assert md_rows["ours"][col] == f"{runs / 'diffusion_spp4'} (Control Module on a box blur)"
    assert md_rows["base_only"][col] == f"{runs / 'diffusion_spp4'} (its base alone: a box blur)"
    assert md_rows["oidn"][col] == "OIDN's built-in weights" and md_rows["noisy"][col] == "–"
    assert md_rows["isik"][col] == str(runs / "isik_spp4")
    assert all("color.variance" in c["keys"] and "normal" in c["keys"] for c in FakeDiffusion.calls)
    assert rows["ours"]["metrics"]["l1"] < rows["noisy"]["metrics"]["l1"]
    assert rows["base_only"]["metrics"]["l1"] > rows["noisy"]["metrics"]["l1"]
    assert rows["ours"]["seconds"]["median"] > rows["ours_skip18"]["seconds"]["median"]
    kinds = [p["kind"] for p in e4["time_vs_error"]]
    assert kinds.count("ours") == 2 and "mc_equal_time" in kinds

    # equal time, pooled: 4·floor(wanted/4) spp, capped at the 16 stored; same image as the curve
    for name in ("ours", "oidn", "isik"):
        et = e4["equal_time"][name]
        for rec in et["per_frame"]:
            wanted = 4 + et["denoise_seconds"] / B
            assert rec["wanted_spp"] == pytest.approx(wanted)
            assert rec["spp"] == min(16, max(4, 4 * math.floor(wanted / 4 + 1e-9)))
            assert rec["capped"] == (4 * math.floor(wanted / 4 + 1e-9) > 16)
    ours_et = e4["equal_time"]["ours"]
    assert ours_et["capped_frames"] == FRAMES                # 0.05 s buys 50 spp > 16 stored
    assert ours_et["metrics"]["l1"] == pytest.approx(mean[2]["l1"], rel=1e-6)
    assert "ours" not in e16["equal_time"]

    md = (out / "eval.md").read_text()
    assert "| method | L1 ↓ | PSNR dB ↑ | SSIM ↑ | FLIP ↓ | HDR-FLIP ↓ | FovVideoVDP JOD ↑ |" in md
    assert "**" in md and "not available: no Isik checkpoint" in md and "CAPPED" in md
    assert "Skipped: not in the store" in md and "LPIPS, DINO, CLIP" in md
    assert "Stability: not run yet" in md and "Warning:** plain MC gains only" not in md   # GT_clean is exact
    saved = json.loads((out / "eval.json").read_text())
    assert saved["meta"]["git"]["commit"] and saved["meta"]["packages"]["pyoidn"] != "not installed"
    assert saved["meta"]["config"]["eval"]["methods"] == methods
    lines = (out / "eval_test_spp4.csv").read_text().splitlines()
    assert lines[0].startswith("method,label,available,reason,l1,psnr")
    assert sum(line.startswith("mc_equal_") for line in lines) == 3


TINY_ISIK = ["clean.epochs=1", "clean.batch_size=2", "clean.crop=8", "clean.crops_per_frame=1", "clean.channels=[8, 8]",
             "clean.embed_channels=8", "clean.affinity_channels=4", "clean.kernel_size=3", "clean.dilations=[1, 2]",
             "clean.device=cpu"]


@pytest.mark.slow
def test_isik_sppany_serves_every_spp_and_stress_frames_are_their_own_group(tmp_path):
    root = make_store(tmp_path / "store", {SCENE: "test", "s00002": "train", "s00003": "val",
                                           "stress_fireflies": "stress"})
    runs, out = tmp_path / "runs", tmp_path / "r"
    proc = cli("train", "--model", "isik", "--spp", "any", "--config", TINY, f"store={root}", f"runs={runs}",
               *TINY_ISIK, "--quiet")
    assert proc.returncode == 0, proc.stderr
    record = json.loads((runs / "isik_sppany" / "model.json").read_text())
    assert record["spp"] == "any" and record["spp_choices"] == [4, 8, 16]    # every pooled power of two
    overrides = [f"store={root}", f"runs={runs}", "eval.methods=[noisy, isik]", "eval.metrics=[l1, psnr]",
                 "eval.equal_time=none", "eval.device=cpu"]

    def isik_rows():
        result = run_eval(load_config(TINY, overrides), spps=[4, 16], out=str(out), quiet=True)
        assert list(result["groups"]) == ["test", "stress"]      # hard cases apart, never averaged in
        assert all(f.startswith("stress_") for f in result["groups"]["stress"]["frames"])
        assert not any(f.startswith("stress_") for f in result["groups"]["test"]["frames"])
        return {spp: result["groups"]["test"]["spp"][spp]["methods"]["isik"] for spp in ("4", "16")}

    rows = isik_rows()
    assert all(r["available"] and r["checkpoint"] == str(runs / "isik_sppany") and r["failed_frames"] == 0
               for r in rows.values())
    assert f"| {runs / 'isik_sppany'} |" in (out / "eval.md").read_text()
    save_untrained_isik(runs / "isik_spp4")                  # a per-spp run wins where it exists
    assert [r["checkpoint"] for r in isik_rows().values()] == [str(runs / "isik_spp4"), str(runs / "isik_sppany")]

    record["spp_choices"] = [4, 8]                           # isik_sppany never saw 16 spp: not used there
    (runs / "isik_sppany" / "model.json").write_text(json.dumps(record))
    rows = isik_rows()
    assert rows["4"]["available"] and not rows["16"]["available"]
    assert "SPP=any" in rows["16"]["reason"] and "isik_spp16" in rows["16"]["reason"]
    md = (out / "eval.md").read_text()
    assert "| Isik et al. (`isik`) | – | – |" in md.split("### test, 16 spp")[1]
    assert "not available: `isik`" in md.split("\n\n")[1].split("At 16 spp")[1]     # in the headline, too
    with open(out / "eval_test_spp16.csv", newline="") as f:
        isik16 = next(r for r in csv.DictReader(f) if r["method"] == "isik")
    assert isik16["available"] == "False" and isik16["reason"].startswith("no Isik checkpoint") and isik16["l1"] == ""
    assert isik16["l1_vs_noisy_hi"] == ""                    # a full row, interval columns empty
    frames_csv = (out / "eval_frames.csv").read_text()
    assert "test,16,isik," not in frames_csv and "test,4,isik,s00001/000,ok" in frames_csv
    assert "stress,16,noisy,stress_fireflies/001,ok" in frames_csv
    assert list(frame_groups(load_config(TINY, overrides + ["eval.stress=false"]), Store(root))) == ["test"]


@pytest.mark.slow
def test_identical_method_reports_psnr_inf(store_root, tmp_path, monkeypatch):
    """A 'denoiser' that returns GT_clean: PSNR inf in the JSON (as the string) and the table."""
    import mcdenoise.evaluate.methods as em

    class Oracle(em.Method):
        name, device = "ours", "cpu"

        def __init__(self, store):
            self.store = store

        def denoise(self, buffers):
            for key in self.store.frames("test"):
                img = self.store.read(key.scene, key.frame, 4)["color"]
                if np.array_equal(img, buffers["color"]):
                    return self.store.read_image(key.scene, key.frame, "gt_clean")[0]["color"]
            raise AssertionError("unknown frame")

    monkeypatch.setattr(em.Loader, "load", lambda self, name, spp: Oracle(Store(store_root)))
    cfg = load_config(TINY, [f"store={store_root}", f"runs={tmp_path}", "eval.methods=[ours]",
                             "eval.equal_time=none", "eval.metrics=[l1, psnr, ssim]"])
    result = run_eval(cfg, spps=[4], out=str(tmp_path / "r"), quiet=True)
    m = result["groups"]["test"]["spp"]["4"]["methods"]["ours"]["metrics"]
    assert m == {"l1": 0.0, "psnr": math.inf, "ssim": 1.0}
    assert json.loads((tmp_path / "r" / "eval.json").read_text())["groups"]["test"]["spp"]["4"]["methods"][
        "ours"]["metrics"]["psnr"] == "inf"
    # the same value on every frame: a zero-width interval; inf has none
    assert "| **0.0000** ± 0.0000 | **inf** | **1.0000** ± 0.0000 |" in (tmp_path / "r" / "eval.md").read_text()


@pytest.mark.slow
def test_cli_missing_store_is_a_clear_error(tmp_path):
    proc = cli("eval", "--config", TINY, f"store={tmp_path / 'nope'}", f"runs={tmp_path}", "--out", tmp_path / "r")
    assert proc.returncode == 2
    assert "no dataset store here" in proc.stderr and str(tmp_path / "nope") in proc.stderr
    proc = cli("eval", "--config", TINY, f"store={tmp_path}", "eval.methods=[noisy, magic]")
    assert proc.returncode == 2 and "unknown method 'magic'" in proc.stderr
    proc = cli("eval", "--config", TINY, "eval.equal_time=sometimes")
    assert proc.returncode == 2 and "eval.equal_time" in proc.stderr


def test_cli_needs_gt_clean(store_root, tmp_path):
    import shutil
    root = tmp_path / "store"
    shutil.copytree(store_root, root)
    for p in root.rglob("gt_clean.exr"):
        p.unlink()
    proc = cli("eval", "--config", TINY, f"store={root}", f"runs={tmp_path}", "--out", tmp_path / "r")
    assert proc.returncode == 2 and "make gt-clean" in proc.stderr


SCENE_XML = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="20"/><integer name="height" value="14"/></film></sensor>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
  <emitter type="point"><point name="position" x="2" y="2" z="3"/><rgb name="intensity" value="10"/></emitter>
  <shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.4, 0.2"/></bsdf></shape>
</scene>"""


@pytest.mark.slow
def test_external_scene_rendered_and_reported_separately(tmp_path):
    xml = tmp_path / "ball.xml"
    xml.write_text(SCENE_XML)
    store = tmp_path / "store"
    out = tmp_path / "r"
    proc = cli("eval", "--config", TINY, f"store={store}", f"runs={tmp_path / 'runs'}", "eval.methods=[noisy, oidn]",
               "eval.metrics=[l1, psnr]", "eval.equal_time=render", "eval.equal_time_max_spp=12",
               "eval.equal_time_methods=[oidn]", "--spp", "4,16", "--scene", xml, "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "## external: 1 frame(s), reference gt1" in proc.stdout
    assert "eval: 1 frames in 1 group(s)" in proc.stdout
    result = json.loads((out / "eval.json").read_text())
    g = result["groups"]["external"]
    assert g["frames"] == ["ext_ball/000"] and list(result["groups"]) == ["external"]
    assert [p["spp"] for p in g["mc_curve"]["ext_ball/000"]] == [4, 8, 16, 64]
    et = g["spp"]["4"]["equal_time"]["oidn"]["per_frame"][0]
    # rendered by the dataset's renderer at the equal-time spp (capped at 12), cached in the store
    assert et["spp"] == min(12, round(et["wanted_spp"])) and et["measured_seconds"] > 0
    assert et["capped"] == (round(et["wanted_spp"]) > 12)
    assert (store / "scenes" / "ext_ball" / "000" / f"mc{et['spp']:05d}.exr").exists()
    assert isinstance(et["metrics"]["psnr"], float) and et["metrics"]["psnr"] > 5
    rows = g["spp"]["16"]["methods"]
    assert rows["oidn"]["failed_frames"] == 0 and rows["oidn"]["seconds"]["median"] > 0
    assert set(rows["noisy"]["metrics"]) == {"l1", "psnr"}


@pytest.mark.slow
def test_realizations_average_each_frame_over_disjoint_stack_groups(store_root, tmp_path):
    """eval.realizations=N: a frame's metrics are the mean over its disjoint stack groups (as many as the
    stacks hold at that spp), scored one by one here with the store's own reader."""
    from mcdenoise.pipeline.config import ConfigError
    from mcdenoise.pipeline.metrics import psnr

    cfg = load_config(TINY, [f"store={store_root}", f"runs={tmp_path}", "eval.methods=[noisy, oidn]",
                             "eval.equal_time=none", "eval.metrics=[l1, psnr]", "eval.realizations=8"])
    result = run_eval(cfg, spps=[4, 8, 16], out=str(tmp_path / "r"), quiet=True)
    store = Store(store_root)
    for spp, groups in ((4, 4), (8, 2), (16, 1)):
        rows = result["groups"]["test"]["spp"][str(spp)]["methods"]
        for key, rec in zip(sorted(store.frames("test"), key=str), rows["noisy"]["per_frame"]):
            ref = store.read_image(key.scene, key.frame, "gt_clean", ["color"])[0]["color"]
            k = spp // 4
            each = [psnr(store.read(key.scene, key.frame, spp, stacks=list(range(g * k, (g + 1) * k)))["color"], ref)
                    for g in range(groups)]
            assert rec["metrics"]["psnr"] == pytest.approx(np.mean(each), abs=1e-9)
            assert rec.get("realizations", 1) == groups
            assert len(set(np.round(each, 6))) == groups        # the groups are different noise draws
        assert all(r["status"] == "ok" for r in rows["oidn"]["per_frame"])
    one = run_eval(load_config(TINY, [f"store={store_root}", f"runs={tmp_path}", "eval.methods=[noisy]",
                                      "eval.equal_time=none", "eval.metrics=[psnr]"]),
                   spps=[4], out=str(tmp_path / "one"), quiet=True)
    first = one["groups"]["test"]["spp"]["4"]["methods"]["noisy"]["per_frame"][0]
    key = sorted(store.frames("test"), key=str)[0]
    ref = store.read_image(key.scene, key.frame, "gt_clean", ["color"])[0]["color"]
    assert first["metrics"]["psnr"] == pytest.approx(psnr(store.read(key.scene, key.frame, 4)["color"], ref))
    assert "up to 8 noise realizations" in (tmp_path / "r" / "eval.md").read_text()
    assert "noise realizations" not in (tmp_path / "one" / "eval.md").read_text()
    with pytest.raises(ConfigError, match="realizations"):
        load_config(TINY, ["eval.realizations=0"])
