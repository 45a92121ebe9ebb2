"""The denoiser reads like OIDN's training kit: short paths from a command to its work, short functions.

A reader follows ``python -m pipeline denoise --exr IN --out OUT`` to its first convolution, and ``train
--model diffusion`` to its first optimiser step, through the project files whose functions run on the way
(class bodies and module-level comprehensions count: importing such a file runs them; ``<module>`` code and
files under tests/ or site-packages do not). ``path_files`` records them with a profiler in a fresh
process. Targets: at most 12 files for ``denoise --exr``, at most 15 for ``train``; and no function over 60
lines in the package outside the integrator (``render/integrator.py``, one Mitsuba integrator class whose
``sample`` is the estimator written out).
"""
from __future__ import annotations

import ast
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import TINY

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "render", "clean", "train", "evaluate", "mcdenoise", "tools")
LONGEST = 60
EXEMPT = {"render/integrator.py"}

# Runs `python -m pipeline ARGS` under a profiler until the first convolution (UNTIL=conv) or optimiser step
# (UNTIL=step); prints the project files whose functions ran, in order, as JSON.
TRACER = r"""
import json, os, runpy, sys
repo, until, args = sys.argv[1], sys.argv[2], sys.argv[3:]
order = []
class Done(BaseException):
    pass
seen = {}
def prof(frame, event, arg):
    if event == "c_call":
        if until == "conv" and getattr(arg, "__name__", "") in ("conv2d", "_conv_forward"):
            raise Done
        return
    if event != "call":
        return
    code = frame.f_code
    if until == "conv" and code.co_name == "_conv_forward":
        raise Done
    if until == "step" and code.co_name == "step" and "optim" in code.co_filename:
        raise Done
    name = code.co_filename
    if code.co_name == "<module>" or seen.get(name, True) is None:
        return
    if name not in seen:      # a file is classified once: in the project (its path) or not (None)
        f = os.path.realpath(name)
        inside = (not name.startswith("<") and f.startswith(repo + os.sep) and "/.venv/" not in f
                  and "/tests/" not in f and "site-packages" not in f)
        seen[name] = os.path.relpath(f, repo) if inside else None
    rel = seen[name]
    if rel is not None and rel not in order:
        order.append(rel)
sys.argv = ["pipeline"] + args
reached = False
sys.setprofile(prof)
try:
    runpy.run_module("pipeline", run_name="__main__")
except Done:
    reached = True
except SystemExit:
    pass
finally:
    sys.setprofile(None)
print(json.dumps({"reached": reached, "files": order}))
"""


def path_files(until: str, *args: str) -> list[str]:
    """The project files a command's functions pass through before its first ``until`` ('conv' or 'step')."""
    proc = subprocess.run([sys.executable, "-c", TRACER, str(ROOT), until, *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=900)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["reached"], f"never reached the first {until}: {proc.stderr[-2000:]}"
    return out["files"]


def long_functions(root: Path = ROOT, packages=PACKAGES, limit: int = LONGEST) -> list[str]:
    """``file:line name (lines)`` of every function longer than ``limit`` lines (docstring included)."""
    found = []
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root).as_posix()
            if rel in EXEMPT:
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = node.end_lineno - node.lineno + 1
                    if n > limit:
                        found.append(f"{rel}:{node.lineno} {node.name} ({n} lines)")
    return found


def test_long_functions_are_found(tmp_path):
    """The scan itself: a 61-line method is found, a 60-line function is not, nor anything in the integrator."""
    def source(name: str, lines: int, indent: str = "") -> str:
        return f"{indent}def {name}():\n" + f"{indent}    x = 1\n" * (lines - 1)
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "a.py").write_text(source("fits", 60) + "\n\nclass A:\n" + source("long", 61, "    "))
    (tmp_path / "render").mkdir()
    (tmp_path / "render" / "integrator.py").write_text(source("sample", 98))
    assert long_functions(tmp_path, ("pkg", "render")) == ["pkg/a.py:64 long (61 lines)"]


def test_no_function_over_60_lines_outside_the_integrator():
    assert long_functions() == []


@pytest.mark.slow
def test_denoise_exr_reaches_its_first_convolution_through_at_most_12_files(tmp_path):
    from mcdenoise.pipeline.exr import write_image

    rng = np.random.default_rng(0)
    shape = (32, 48)
    buffers = {"color": rng.gamma(2.0, 0.2, (*shape, 3)).astype(np.float32),
               "albedo": rng.uniform(0.1, 0.9, (*shape, 3)).astype(np.float32),
               "normal": rng.normal(0.0, 1.0, (*shape, 3)).astype(np.float32)}
    buffers["normal"] /= np.linalg.norm(buffers["normal"], axis=2, keepdims=True)
    buffers.update({f"{k}.variance": np.zeros_like(v) for k, v in list(buffers.items())})
    write_image(tmp_path / "in.exr", buffers, meta={"spp": 4})
    files = path_files("conv", "denoise", "--exr", tmp_path / "in.exr", "--out", tmp_path / "out.exr")
    assert "train/model.py" in files and "train/infer.py" in files
    assert len(files) <= 12, files


@pytest.mark.slow
def test_train_reaches_its_first_optimiser_step_through_at_most_15_files(cleaned, tmp_path):
    store, runs = cleaned
    mine = tmp_path / "runs"
    shutil.copytree(runs, mine)
    files = path_files("step", "train", "--model", "diffusion", "--spp", "4", "--config", TINY, f"store={store}",
                       f"runs={mine}", "diffusion.crop=16", "diffusion.batch_size=4", "--quiet")
    assert "train/train.py" in files and "train/loss.py" in files
    assert len(files) <= 15, files
