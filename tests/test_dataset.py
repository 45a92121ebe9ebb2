"""The dataset stage end to end on configs/tiny.yaml, through the real command line.

Uses the tiny store rendered once per test run (tests/conftest.py) and checks the layout, manifests
and splits, resume after SIGKILL, the Ray executor and the errors users will meet.
"""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.exr import read_image
from mcdenoise.pipeline.inspect import _format_gt
from mcdenoise.pipeline.store import Store, image_names
from tests.helpers import ROOT, TINY, all_keys, assert_same_store, cli


def test_tiny_dataset_layout(tiny_store):
    root, proc = tiny_store
    assert "dataset: 6 frames (6 rendered, 0 already done, 0 failed)" in proc.stdout
    store = Store(root)
    m = store.manifest()
    splits = m["splits"]
    assert sorted(splits["train"] + splits["val"] + splits["test"]) == sorted(m["scenes"])
    assert len(splits["val"]) >= 1 and len(splits["test"]) >= 1
    seeds = []
    for key in store.frames():
        rec = store.frame_record(key.scene, key.frame)
        assert sorted(rec["images"]) == sorted(image_names(4))
        for name, img in rec["images"].items():
            assert img["spp"] == (64 if name.startswith("gt") else 4)
            seeds.append(img["seed"])
            assert img["sha256"] and img["bytes"] > 0
        sm = store.scene_manifest(key.scene)
        assert sm["description"] and sm["packages"]["mitsuba"]
        assert str(key.frame) in sm["rendered"]
    assert len(seeds) == len(set(seeds)), "every image of the dataset needs its own seed"


def test_every_buffer_is_restored_and_finite(tiny_store):
    root, _ = tiny_store
    store = Store(root)
    key = store.frames()[0]
    img, rec = store.read_image(key.scene, key.frame, "gt1")
    assert set(img) == set(all_keys())
    for k, v in img.items():
        assert v.dtype == np.float32 and np.all(np.isfinite(v)), k
        assert v.shape == (24, 32, v.shape[2])
    total = sum(img[c] for c in schema.RADIANCE_COMPONENTS)
    np.testing.assert_allclose(total, img["color"], rtol=1e-4, atol=1e-4)


def test_stacks_average_to_spp(tiny_store):
    root, _ = tiny_store
    store = Store(root)
    key = store.frames()[0]
    b16 = store.read(key.scene, key.frame, 16)
    stacks = [store.read_image(key.scene, key.frame, f"s{k:02d}")[0]["color"] for k in range(4)]
    np.testing.assert_allclose(b16["color"], np.mean(stacks, axis=0), rtol=1e-5, atol=1e-7)


def test_rerun_skips_finished_frames(tiny_store):
    root, _ = tiny_store
    before = {p: p.stat().st_mtime_ns for p in root.rglob("*.exr")}
    proc = cli("dataset", "--config", TINY, f"store={root}")
    assert "(0 rendered, 6 already done, 0 failed)" in proc.stdout
    assert {p: p.stat().st_mtime_ns for p in root.rglob("*.exr")} == before


def test_inspect_reports_frames_and_constants(tiny_store):
    root, _ = tiny_store
    proc = cli("inspect", root, "--json")
    report = json.loads(proc.stdout)
    assert report["frames"] == 6 and report["frames_complete"] == 6
    assert report["images"] == 6 * 6 and report["nonfinite"] == 0
    key = Store(root).frames()[0]
    detail = json.loads(cli("inspect", root, "--frame", f"{key.scene}/000", "--json").stdout)["frame"]
    gt1 = detail["images"]["gt1"]
    assert gt1["spp"] == 64 and {"diffuse_direct.R", "R"} <= set(gt1["channels"])   # R: the beauty's half view
    assert set(gt1["channels"]).isdisjoint(gt1["constants"])
    text = cli("inspect", root).stdout
    assert "6/6 frames complete" in text
    # every image counted under its encoding (the tiny config writes the compact one, beauty derived, R, G, B its view)
    assert report["encodings"] == {"compact, beauty view": 6 * 6}
    assert "encodings (images): compact, beauty view: 36" in text


def test_inspect_says_identical_instead_of_the_json_psnr_ceiling():
    stats = {"frames": 2, "spp_min": 64, "spp_max": 64, "spp_mean": 64.0, "psnr_gt1_gt2_median": 999.0,
             "psnr_gt1_gt2_min": 41.5, "estimated_psnr_median": None}
    (line,) = _format_gt({**stats, "by_family": {}})
    assert "median identical (min 41.5 dB)" in line and "estimated PSNR median n/a" in line and "999" not in line


@pytest.mark.slow
def test_kill_and_resume_matches_uninterrupted_run(tiny_store, tmp_path):
    """SIGKILL mid-run at several moments; the rerun completes and equals an uninterrupted run."""
    reference, _ = tiny_store
    root = tmp_path / "killed"
    args = [sys.executable, "-m", "pipeline", "dataset", "--config", str(TINY), f"store={root}", "--quiet"]
    for kill_after_images in (1, 5, 14):
        proc = subprocess.Popen(args, cwd=ROOT, start_new_session=True)
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None:
            if len(list(root.rglob("*.exr"))) >= kill_after_images:
                break
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGKILL)   # the worker processes too
        proc.wait()
    survivors = {p: p.stat().st_mtime_ns for p in root.rglob("*.exr")}
    assert survivors, "the kills came before anything was written; the test did not test resume"
    cli("dataset", "--config", TINY, f"store={root}", "--quiet")
    for p, mtime in survivors.items():   # nothing already written was redone
        assert p.stat().st_mtime_ns == mtime, p
    assert not list(root.rglob("*.tmp")), "temporary files left behind"
    assert_same_store(reference, root)


@pytest.mark.slow
def test_shards_cover_the_dataset(tiny_store, tmp_path):
    reference, _ = tiny_store
    root = tmp_path / "sharded"
    for i in range(3):
        cli("dataset", "--config", TINY, f"store={root}", "--shard", f"{i}/3", "--quiet")
    assert_same_store(reference, root)


@pytest.mark.slow
def test_ray_executor_writes_the_same_files(tiny_store, tmp_path):
    reference, _ = tiny_store
    root = tmp_path / "ray"
    cli("dataset", "--config", TINY, f"store={root}", "executor.kind=ray", "executor.workers=2", "--quiet")
    assert_same_store(reference, root)


def test_unknown_config_key_is_a_clear_error(tmp_path):
    proc = cli("dataset", "--config", TINY, f"store={tmp_path}/s", "dataset.scene=3", check=False)
    assert proc.returncode == 2
    assert "unknown config key dataset.scene" in proc.stderr
    assert not (tmp_path / "s").exists()


def test_store_made_with_another_config_is_refused(tiny_store):
    root, _ = tiny_store
    proc = cli("dataset", "--config", TINY, f"store={root}", "dataset.gt_spp=128", check=False)
    assert proc.returncode == 2 and "different 'dataset'" in proc.stderr


@pytest.mark.slow
def test_unreadable_scene_xml_is_a_clear_error(tmp_path):
    bad = tmp_path / "broken.xml"
    bad.write_text("<scene version='3.0.0'><shape type='nosuchshape'/></scene>")
    proc = cli("render-scene", bad, "--store", tmp_path / "ext", "--config", TINY, check=False)
    assert proc.returncode == 2
    assert "broken.xml" in proc.stderr
    assert not (tmp_path / "ext").exists()          # the store this call would have made: not left behind


@pytest.mark.slow
def test_failed_scene_leaves_an_existing_store_as_it_was(tmp_path, tiny_store):
    """A bad scene added to a dataset store: no manifest entry, no scene folder, nothing else touched."""
    root, _ = tiny_store
    before = {p: p.read_bytes() for p in Path(root).rglob("*") if p.is_file() and p.suffix == ".json"}
    files = sorted(Path(root).rglob("*"))
    bad = tmp_path / "broken.xml"
    bad.write_text("<scene version='3.0.0'><shape type='nosuchshape'/></scene>")
    proc = cli("render-scene", bad, "--store", root, "--config", TINY, check=False)
    assert proc.returncode == 2 and "broken.xml" in proc.stderr
    assert sorted(Path(root).rglob("*")) == files
    assert all(p.read_bytes() == data for p, data in before.items())


@pytest.mark.slow
def test_render_scene_writes_a_test_frame(tmp_path):
    xml = tmp_path / "box.xml"
    xml.write_text("""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="20"/><integer name="height" value="16"/>
      <rfilter type="gaussian"/></film></sensor>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
</scene>""")
    cli("render-scene", xml, "--store", tmp_path / "ext", "--config", TINY)
    store = Store(tmp_path / "ext")
    assert store.manifest()["splits"]["external"] == ["ext_box"]
    img, rec = store.read_image("ext_box", 0, "gt1")
    assert img["color"].shape == (16, 20, 3)
    assert rec["spp"] == 64
    assert img["color"][8, 10].mean() > 0.05         # the sphere is lit
    assert np.all(img["transmission"] == 0)          # no transmissive material: constant, left out
    assert "transmission.Y" in rec["constants"]



def test_a_scenes_own_path_depths_are_read_from_its_integrator(tmp_path):
    """``scene_depths``: max_depth and rr_depth of the first integrator that sets them (nested too), ``$name``
    values from -D or the XML's defaults; nothing for a scene without them or an unreadable file."""
    from mcdenoise.render.external import scene_depths

    xml = tmp_path / "s.xml"
    xml.write_text("""<scene version="3.0.0"><default name="depth" value="6"/>
  <integrator type="aov"><string name="aovs" value="nn:sh_normal"/>
    <integrator type="path"><integer name="max_depth" value="$depth"/><integer name="rr_depth" value="3"/></integrator>
  </integrator></scene>""")
    assert scene_depths(str(xml), {}) == {"max_depth": 6, "rr_depth": 3}
    assert scene_depths(str(xml), {"depth": "12"}) == {"max_depth": 12, "rr_depth": 3}
    (tmp_path / "none.xml").write_text('<scene version="3.0.0"><integrator type="path"/></scene>')
    assert scene_depths(str(tmp_path / "none.xml"), {}) == {}
    (tmp_path / "bad.xml").write_text("<scene")
    assert scene_depths(str(tmp_path / "bad.xml"), {}) == {}


@pytest.mark.slow
def test_render_scene_keeps_the_scenes_own_max_depth_and_says_so(tmp_path):
    xml = tmp_path / "deep.xml"
    xml.write_text("""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="12"/><integer name="height" value="8"/>
      <rfilter type="box"/></film></sensor>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
</scene>""")
    proc = cli("render-scene", xml, "--store", tmp_path / "ext", "--config", TINY)
    assert "the scene's integrator max_depth=3 kept (render.max_depth=5" in proc.stdout
    assert "denoise --store" in proc.stdout and "--frame ext_deep/000" in proc.stdout
    assert Store(tmp_path / "ext").scene_manifest("ext_deep")["integrator"]["max_depth"] == 3


@pytest.mark.slow
def test_scene_parameters_are_given_with_D_as_on_mitsubas_command_line(tmp_path):
    """``-D name=value`` fills the XML's ``$name`` (Mitsuba's -D); a parameter without a value is named in the
    error with the way to give it, and the store is left as it was."""
    xml = tmp_path / "params.xml"
    xml.write_text("""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
    <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/></film></sensor>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
</scene>""")
    proc = cli("render-scene", xml, "-D", "spp=64", "--store", tmp_path / "ext", "--config", TINY, check=False)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "params.xml" in proc.stderr and "undefined parameter: $res" in proc.stderr
    assert "-D res=VALUE" in proc.stderr and 'DEFINES="res=VALUE"' in proc.stderr
    assert not (tmp_path / "ext").exists()
    proc = cli("render-scene", xml, "-D", "spp=64", "-D", "res=14", "--store", tmp_path / "ext", "--config", TINY,
               "dataset.stacks=1", check=False)
    assert proc.returncode == 0, proc.stderr
    store = Store(tmp_path / "ext")
    assert store.read_image("ext_params", 0, "s00")[0]["color"].shape == (14, 14, 3)
    assert store.scene_manifest("ext_params")["description"]["defines"] == {"res": "14", "spp": "64"}
    proc = cli("render-scene", xml, "-D", "res", "--store", tmp_path / "x", "--config", TINY, check=False)
    assert proc.returncode == 2 and "-D 'res': expected NAME=VALUE" in proc.stderr
    proc = cli("eval", "-D", "spp=4", "--config", TINY, f"store={tmp_path / 'x'}", check=False)
    assert proc.returncode == 2 and "no --scene was given" in proc.stderr


def test_make_eval_passes_DEFINES_as_scene_parameters_not_config_overrides():
    """``make eval SCENES=... DEFINES="spp=64 res=256"``: each word a -D, none a config override."""
    proc = subprocess.run(["make", "-n", "eval", "VENV=.venv-none", "SCENES=a.xml b.xml", "DEFINES=spp=64 res=256",
                           "dataset.scenes=4"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    # (under `make test` the inner make also prints "Entering/Leaving directory" lines)
    command = next(line for line in proc.stdout.splitlines() if " -m pipeline eval " in line)
    assert command.split(" -m pipeline ", 1)[1].split() == [
        "eval", "--config", "configs/default.yaml", "dataset.scenes=4", "--scene", "a.xml", "--scene", "b.xml",
        "-D", "spp=64", "-D", "res=256"]


_CAMERA = """<sensor type="{camera}"><float name="fov" value="45"/>{lens}
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="12"/><integer name="height" value="10"/></film></sensor>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>"""


@pytest.mark.slow
def test_what_the_render_leaves_out_of_a_users_scene_is_said(tmp_path):
    """A thin-lens camera and a participating medium render without depth of field and without the
    medium; render-scene says so instead of leaving the user to find out from the images."""
    xml = tmp_path / "lens.xml"
    lens = '<float name="aperture_radius" value="0.1"/><float name="focus_distance" value="4"/>'
    xml.write_text(f"""<scene version="3.0.0">{_CAMERA.format(camera="thinlens", lens=lens)}
  <shape type="sphere"><bsdf type="dielectric"/>
    <medium type="homogeneous" name="interior"><float name="sigma_t" value="2"/></medium></shape>
</scene>""")
    proc = cli("render-scene", xml, "--store", tmp_path / "ext", "--config", TINY)
    assert "thin-lens camera is rendered as a pinhole" in proc.stdout
    assert "1 participating medium is not rendered" in proc.stdout
    assert Store(tmp_path / "ext").frame_record("ext_lens", 0)["scene_notes"] == [
        line.split("note: ", 1)[1] for line in proc.stdout.splitlines() if "note: " in line]

    plain = tmp_path / "plain.xml"
    plain.write_text(f"""<scene version="3.0.0">{_CAMERA.format(camera="perspective", lens="")}
  <shape type="sphere"><bsdf type="diffuse"/></shape></scene>""")
    proc = cli("render-scene", plain, "--store", tmp_path / "ext", "--config", TINY)
    assert "note:" not in proc.stdout


@pytest.mark.slow
def test_a_scene_mitsuba_cannot_render_gets_mitsubas_reason(tmp_path):
    """Mitsuba loads a bump map on a procedural texture but cannot render it; the error is the
    plugin's own message with the file, not drjit's "custom differentiable operation (see above)"."""
    xml = tmp_path / "bump.xml"
    xml.write_text(f"""<scene version="3.0.0">{_CAMERA.format(camera="perspective", lens="")}
  <shape type="sphere"><bsdf type="bumpmap"><texture type="checkerboard" name="arbitrary"/>
    <bsdf type="diffuse"/></bsdf></shape></scene>""")
    proc = cli("render-scene", xml, "--store", tmp_path / "ext", "--config", TINY, check=False)
    assert proc.returncode == 2
    assert "bump.xml: Mitsuba failed rendering" in proc.stderr and "eval_1_grad" in proc.stderr
    assert "see above" not in proc.stderr
    assert not (tmp_path / "ext").exists()

def test_corrupt_image_in_store_names_the_file(tiny_store, tmp_path):
    root, _ = tiny_store
    store = Store(root)
    key = store.frames()[0]
    path = store.image_path(key.scene, key.frame, "s01")
    data = path.read_bytes()
    copy = tmp_path / "s01.exr"
    copy.write_bytes(data[: len(data) - 200])
    with pytest.raises(Exception, match=r"s01\.exr"):
        read_image(copy)


@pytest.mark.slow
def test_stress_presets_render_finite_with_counts(tmp_path):
    """Every stress preset renders through the real integrator; NaN/Inf, if any, are counted."""
    from mcdenoise.render.scene import STRESS_PRESETS

    root = tmp_path / "stress"
    cli("dataset", "--config", TINY, f"store={root}", "dataset.scenes=1", "dataset.frames=1",
        "dataset.stress=[all]", "--quiet")
    store = Store(root)
    stress = store.manifest()["splits"]["stress"]
    assert sorted(stress) == sorted(f"stress_{p}" for p in STRESS_PRESETS)
    for scene in stress:
        rec = store.frame_record(scene, 0)
        assert rec is not None, scene
        counted = 0
        for name in rec["images"]:
            img, header = store.read_image(scene, 0, name)
            assert all(np.all(np.isfinite(v)) for v in img.values()), (scene, name)
            assert isinstance(header["nonfinite"], dict)
            counted += sum(header["nonfinite"].values())
        assert rec["nonfinite"] == counted
    fills = store.read_image("stress_emitter_fills_view", 0, "gt1")[0]
    assert fills["emission"].mean() > 0.5 * fills["color"].mean()   # the emitter is what the camera sees
    empty = store.read_image("stress_empty_environment", 0, "gt1")[0]
    assert np.all(empty["depth"] == 0) and np.all(empty["normal"] == 0)  # nothing but background
