"""The stability suite on its small cases (the 1920×1080 case is left out through its parameter)."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mcdenoise.evaluate.methods as em
from mcdenoise.evaluate.harness import repaired_inputs, run_method
from mcdenoise.evaluate.stability import CASES, LARGE, run_stability, synthetic_buffers
from mcdenoise.pipeline import schema
from mcdenoise.pipeline.config import load_config
from tests.helpers import all_keys, save_untrained_isik

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.yaml"


def test_synthetic_buffers_have_every_schema_channel():
    b = synthetic_buffers(17, 33, seed=0)
    assert sorted(b) == sorted(all_keys())
    for buf in schema.BUFFERS:
        assert b[buf.name].shape == (17, 33, buf.size) and b[buf.name].dtype == np.float32
        assert b[schema.variance_name(buf.name)].shape == (17, 33, buf.size)
    parts = sum(b[k] for k in schema.RADIANCE_COMPONENTS)
    np.testing.assert_allclose(parts, b["color"], rtol=1e-5, atol=1e-7)   # exact decomposition
    assert CASES["size_1920x1080"] and "size_1920x1080" in LARGE


def test_every_case_every_method(tmp_path):
    runs = tmp_path / "runs"
    save_untrained_isik(runs / "isik_spp4")
    cfg = load_config(TINY, [f"runs={runs}", "eval.methods=[noisy, oidn, oidn_color, isik, ours]", "eval.device=cpu",
                             "diffusion.shipped=false"])   # ours has no run and no shipped fallback here
    data = run_stability(cfg, large=False, out=tmp_path / "r", quiet=True)
    assert list(data["cases"]) == [c for c in CASES if c not in LARGE]
    for case, row in data["results"].items():
        for name in ("noisy", "oidn", "oidn_color", "isik"):
            cell = row[name]
            assert cell["status"] == "ok", (case, name, cell)
            assert cell["seconds"] >= 0 and np.isfinite([cell["out_min"], cell["out_max"], cell["out_mean"]]).all()
        assert row["ours"] == {"status": "not available"}
    assert "no diffusion checkpoint" in data["unavailable"]["ours"]   # and the reason says how to make one
    assert "make train SPP=4" in data["unavailable"]["ours"]
    # shapes kept, including odd and non-square sizes
    assert data["results"]["size_33x17"]["isik"]["shape"] == [17, 33, 3]
    assert data["results"]["size_64x24"]["oidn"]["shape"] == [24, 64, 3]
    assert data["results"]["size_8x8"]["oidn_color"]["shape"] == [8, 8, 3]
    # NaN/Inf are repaired and counted exactly: the count is the number of bad values built in
    bad = sum(int((~np.isfinite(v)).sum()) for v in CASES["nan_inf"][1]().values())
    assert bad > 100 and data["input_repaired"]["nan_inf"] == bad
    assert data["input_repaired"]["all_black"] == 0
    # black in -> (near) black out; 1e5 in -> about 1e5 out
    assert data["results"]["all_black"]["noisy"]["out_max"] == 0.0
    assert data["results"]["radiance_1e5"]["oidn"]["out_mean"] == pytest.approx(1e5, rel=0.05)
    md = (tmp_path / "r" / "stability.md").read_text()
    assert "| nan_inf:" in md and "n/a" in md and "`isik`" in md
    table = [line for line in md.splitlines() if line.startswith("|")]
    cells = {line.replace("\\|", "").count("|") for line in table}
    assert len(table) == 2 + len(data["cases"]) and cells == {3 + 5 + 1}       # '|n|' is escaped
    assert json.loads((tmp_path / "r" / "stability.json").read_text())["spp"] == 4


@pytest.mark.slow
def test_the_shipped_model_is_finite_on_every_case(tmp_path):
    """`ours` with no run of the config's own falls back to train/shipped: finite on every stiff and
    extreme case, black in gives black out, 1e5 in keeps about 1e5 (the model's range is clamped and
    says so)."""
    cfg = load_config(TINY, [f"runs={tmp_path / 'none'}", "eval.methods=[ours]", "eval.device=cpu"])
    data = run_stability(cfg, large=False, out=tmp_path / "r", quiet=True)
    for case, row in data["results"].items():
        cell = row["ours"]
        assert cell["status"] == "ok", (case, cell)
        assert np.isfinite([cell["out_min"], cell["out_max"], cell["out_mean"]]).all() and cell["out_min"] >= 0
    assert data["results"]["all_black"]["ours"]["out_max"] == 0.0
    assert data["results"]["radiance_1e5"]["ours"]["out_mean"] == pytest.approx(1e5, rel=0.05)


class _Raises(em.Method):
    name = "raises"

    def denoise(self, buffers):
        raise RuntimeError("out of memory")


class _NaNs(em.Method):
    name = "nans"

    def denoise(self, buffers):
        out = buffers["color"].copy()
        out[0, 0, 0] = np.nan
        return out


class _Crops(em.Method):
    name = "crops"

    def denoise(self, buffers):
        return buffers["color"][:-1]


class _Spy(em.Method):
    name = "spy"
    seen_nonfinite = 0

    def denoise(self, buffers):
        _Spy.seen_nonfinite += sum(int((~np.isfinite(v)).sum()) for v in buffers.values())
        return buffers["color"]


def test_failures_are_reported_not_raised(tmp_path, monkeypatch):
    fakes = {"noisy": _Raises(), "oidn": _NaNs(), "oidn_color": _Crops(), "isik": _Spy()}
    monkeypatch.setattr(em.Loader, "load", lambda self, name, spp: fakes[name])
    cfg = load_config(TINY, ["eval.methods=[noisy, oidn, oidn_color, isik]"])
    data = run_stability(cfg, large=False, out=tmp_path, quiet=True)
    row = data["results"]["nan_inf"]
    assert row["noisy"]["status"] == "error: RuntimeError: out of memory"
    assert row["oidn"]["status"] == "1 non-finite output values"
    assert row["oidn_color"]["status"].startswith("error: output shape (63, 64, 3), expected (64, 64, 3)")
    assert row["isik"]["status"] == "ok"
    assert _Spy.seen_nonfinite == 0            # the method never saw a NaN or Inf
    md = (tmp_path / "stability.md").read_text()
    assert md.count("**FAIL**") == 3 * len(data["cases"])


def test_harness_repairs_a_copy_and_times():
    b = synthetic_buffers(8, 8)
    b["color"][0, 0] = [np.nan, np.inf, -np.inf]
    fixed, counts = repaired_inputs(b)
    assert counts == {"color": 3} and np.isnan(b["color"][0, 0, 0])       # the caller's arrays stay
    assert np.all(fixed["color"][0, 0] == 0)
    oc = run_method(em.Noisy(), b)
    assert oc.ok and oc.input_repaired == {"color": 3} and oc.seconds >= 0


@pytest.mark.slow
def test_make_stability_cli(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "pipeline", "stability", "--config", str(TINY),
                           "eval.methods=[noisy, oidn_color]", "eval.stability_large=false", "--out", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "# Stability" in proc.stdout and "stability: 9 cases x 2 methods: 18 ok, 0 failed" in proc.stdout
