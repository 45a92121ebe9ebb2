"""`make bench` runs end to end (its numbers are claims for the README, not asserted here)."""
import json

import pytest

from mcdenoise.pipeline.config import load_config
from mcdenoise.render.bench import run_bench
from tests.helpers import TINY


@pytest.mark.slow
def test_bench_writes_its_report(tmp_path):
    cfg = load_config(TINY, [f"store={tmp_path / 'none'}", "dataset.frames=1"])
    result = run_bench(cfg, out=str(tmp_path / "bench"), scenes=1, resolution=32, spp=4, repeats=1)
    report = json.loads((tmp_path / "bench" / "bench.json").read_text())
    assert [r["scene"] for r in report["integrator"]] == ["cornell_box", "random scene 0"]
    assert all(r["ratio_all"] > 0 and r["ratio_needed"] > 0 for r in report["integrator"])
    d = report["dataset"]
    assert d["frames"] == 1 and 0 < d["render_share"] < 1
    assert d["build_share"] > 0 and d["write_share"] > 0
    assert d["gt"]["spp_mean"] == 64 and d["gt"]["render_s"] > 0 and d["gt"]["psnr_gt1_gt2_median"] > 10
    o = report["omission"]
    # Omission can cost bytes on tiny images (the header's JSON vs ZIP-compressed constant
    # channels), so the report must state the measured saving, whatever its sign.
    assert o["images"] == 6 and o["bytes_full"] > 0 and o["bytes_omitted"] > 0
    assert o["render_s_needed"] > 0 and o["render_s_all"] > 0
    md = (tmp_path / "bench" / "bench.md").read_text()
    assert "Split-buffer integrator" in md and "Ground truths (fixed 64 spp): 64 spp on average" in md
    assert f"{o['disk_saving']:.1%} saved" in md and f"{o['time_saving']:.1%} saved" in md
    assert result["omission"] == o
    c = report["compile"]
    assert [(r["scene"], r["frame"], r["kind"]) for r in c["rows"]] == [
        ("s00000", 0, "first"), ("s00000", 1, "later"), ("s00000", 0, "revalued")]
    # the scene's second camera view reuses the kernels its first compiled (or found in drjit's disk cache)
    assert c["rows"][1]["compiled"] == 0 and all(r["kernels"] > 0 and r["render_s"] > 0 for r in c["rows"])
    assert c["scenes_later"] == 1 and c["compiled_scenes_later"] == 0 and c["scenes_revalued"] == 1
    assert "Kernel compilation against rendering" in md
    assert (f"| first frame of a scene | {c['compile_s_first']:.2f} | {c['render_s_first']:.2f} | "
            f"{c['compiled_scenes_first']} of 1 |") in md


def test_revalued_changes_values_not_structure():
    import numpy as np

    from mcdenoise.render.bench import revalued
    from mcdenoise.render.scene import random_scene

    cfg = load_config(TINY)
    desc = random_scene(cfg.scene, 5, 0, 2)
    new = revalued(desc, np.random.default_rng(1))
    assert new["camera"] == desc["camera"] and new["cluster"] == desc["cluster"]
    assert [o["shape"] for o in new["objects"]] == [o["shape"] for o in desc["objects"]]
    assert [o["transform"] for o in new["objects"]] == [o["transform"] for o in desc["objects"]]
    changed = []

    def compare(a, b):
        assert type(a) is type(b)
        if isinstance(a, dict):
            assert a.keys() == b.keys()
            for k in a:
                compare(a[k], b[k])
        elif isinstance(a, list):
            assert len(a) == len(b)
            for x, y in zip(a, b):
                compare(x, y)
        elif isinstance(a, float):
            assert abs(b - a) <= 0.05 * abs(a) * (1 + 1e-12)
            changed.append(a != b)
        else:
            assert a == b                  # ints, strings, booleans, None: the structure
    compare(desc, new)
    assert sum(changed) > 10                # colours, roughness, light strengths moved
