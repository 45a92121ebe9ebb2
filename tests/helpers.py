"""Helpers shared by several test modules: the tiny config, the command line in a subprocess, and
store comparisons. Fixtures live in ``tests/conftest.py``."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.yaml"
# Not deterministic across runs: wall-clock fields. Everything else must match exactly.
TIMING_KEYS = {"render_seconds", "timing", "reused", "reused_images", "skipped"}
# A small but real cleaner/baseline: a few optimisation steps per epoch on the tiny store.
CLEAN_TINY = ["clean.epochs=5", "clean.batch_size=4", "clean.crop=16", "clean.crops_per_frame=8",
              "clean.channels=[8, 8]", "clean.embed_channels=8", "clean.affinity_channels=4",
              "clean.kernel_size=3", "clean.dilations=[1, 2]", "clean.device=cpu"]


def cli(*args, check=True, timeout=600):
    proc = subprocess.run([sys.executable, "-m", "pipeline", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}")
    return proc


def exr_payload(path: Path) -> dict:
    """Pixel data and header record without wall-clock fields."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        chans = {k: v.pixels.copy() for k, v in f.channels().items()}
        rec = json.loads(f.header()["mcdenoise"])
    return {"channels": chans, "record": {k: v for k, v in rec.items() if k not in TIMING_KEYS}}


def assert_same_store(a: Path, b: Path):
    files_a = sorted(p.relative_to(a) for p in a.rglob("*.exr"))
    files_b = sorted(p.relative_to(b) for p in b.rglob("*.exr"))
    assert files_a == files_b and files_a
    for rel in files_a:
        pa, pb = exr_payload(a / rel), exr_payload(b / rel)
        assert pa["record"] == pb["record"], rel
        assert pa["channels"].keys() == pb["channels"].keys(), rel
        for ch in pa["channels"]:
            np.testing.assert_array_equal(pa["channels"][ch], pb["channels"][ch], err_msg=f"{rel}:{ch}")
