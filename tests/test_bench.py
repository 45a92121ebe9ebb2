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
    assert [(r["scene"], r["frame"]) for r in c["rows"]] == [("s00000", 0), ("s00000", 1)]
    # the scene's second camera view reuses the kernels its first compiled (or found in drjit's disk cache)
    assert c["rows"][1]["compiled"] == 0 and all(r["kernels"] > 0 and r["render_s"] > 0 for r in c["rows"])
    assert "Kernel compilation against rendering" in md and f"| first | {c['compile_s_first']:.2f} |" in md
