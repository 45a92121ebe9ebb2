"""Fault injection: SIGKILL the stages at seeded random moments, rerun, compare with an
uninterrupted run.

Kill points come from progress markers (files appearing in the store or the run folder, the
epoch recorded in ``last.safetensors``) plus a seeded random delay, not from bare sleeps, so
they land at the intended stage on a slow or a busy machine. Every killed run is SIGKILLed with
its whole process group (worker processes too), then the same command is rerun to completion:

- ``dataset``: EXR pixels and header records identical to the uninterrupted run (headers carry
  wall-clock ``render_seconds``, so files are compared channel by channel, not byte by byte),
  manifests identical but for timings, ``verify`` clean;
- ``gt-clean``: the cleaner's final weights and optimizer state bitwise equal, the same loss
  history, identical gt_clean images and cleaner.json;
- ``train --model M``: resumed from the last checkpoint with the same per-epoch losses and
  bitwise-equal final weights. ``TRAIN_CASES`` lists the models: the diffusion trainer joins by
  adding one ``TrainCase``;
- a worker process killed mid-frame (local pool and Ray): the task is retried, resumes from the
  images already written, and the dataset completes identical to the reference.

Each test prints its kill points and how they landed.
"""
from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

from pipeline.verify import verify_store
from tests.test_dataset import TIMING_KEYS, TINY, assert_same_store, cli, exr_payload, tiny_store  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]
KILL_SEED = 20261122
# A small but real cleaner/baseline: a few optimisation steps per epoch on the tiny store.
CLEAN_TINY = ["clean.epochs=5", "clean.batch_size=4", "clean.crop=16", "clean.crops_per_frame=8",
              "clean.channels=[8, 8]", "clean.embed_channels=8", "clean.affinity_channels=4",
              "clean.kernel_size=3", "clean.dilations=[1, 2]", "clean.device=cpu"]
# Fields that legitimately differ between two runs: wall-clock times, and what depends on them
# (file bytes and SHA-256 of EXRs whose headers hold a render time), resume bookkeeping, paths.
VOLATILE = TIMING_KEYS | {"seconds", "sha256", "bytes", "store_bytes", "checkpoint"}


# ---- killing ---------------------------------------------------------------------------------

def session_processes(sid: int) -> dict[int, str]:
    """pid -> command line of every live process in session ``sid``."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            fields = stat[stat.rindex(")") + 2:].split()
            if int(fields[3]) == sid and fields[0] != "Z":
                out[int(d.name)] = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except (OSError, ValueError, IndexError):
            continue
    return out


def run_and_kill(args: list[str], ready: Callable[[float], bool], delay: float, timeout: float = 300) -> str:
    """Start ``python -m pipeline ARGS``, SIGKILL its process group ``delay`` s after
    ``ready(seconds since start)`` is true.

    Returns how it ended: 'killed' or 'finished first' (the marker never came before exit).
    """
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", *args], cwd=ROOT, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    start = time.time()
    try:
        while proc.poll() is None and time.time() < start + timeout:
            if ready(time.time() - start):
                time.sleep(delay)
                break
            time.sleep(0.01)
        if proc.poll() is not None:
            return "finished first"
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        return "killed"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def count(root: Path, pattern: str) -> Callable[[], int]:
    return lambda: len(list(root.rglob(pattern))) if root.exists() else 0


def epochs_done(folder: Path, checkpoint: str = "last.safetensors") -> Callable[[], int]:
    def read() -> int:
        try:
            with safe_open(str(folder / checkpoint), framework="pt") as f:
                return int(json.loads(f.metadata()["state"])["epoch"])
        except Exception:  # noqa: BLE001 - not there yet, or replaced while we looked
            return 0
    return read


def kill_series(name: str, args: list[str], points: list[tuple[str, Callable[[float], bool], float]],
                capsys) -> list[str]:
    results = []
    for label, ready, delay in points:
        results.append(run_and_kill(args, ready, delay))
        with capsys.disabled():
            print(f"\n{name}: kill at {label} + {delay:.2f} s: {results[-1]}", end="")
    return results


# ---- comparing -------------------------------------------------------------------------------

def strip(value):
    """A JSON value without the fields in VOLATILE, at any depth."""
    if isinstance(value, dict):
        return {k: strip(v) for k, v in value.items() if k not in VOLATILE}
    if isinstance(value, list):
        return [strip(v) for v in value]
    return value


def assert_same_manifests(a: Path, b: Path) -> None:
    files = sorted(p.relative_to(a) for p in a.rglob("*.json"))
    assert files == sorted(p.relative_to(b) for p in b.rglob("*.json"))
    for rel in files:
        ja, jb = (json.loads((r / rel).read_text()) for r in (a, b))
        if rel.name == "dataset.json":
            ja["config"].pop("store"), jb["config"].pop("store")
        assert strip(ja) == strip(jb), rel


def assert_verified(root: Path) -> None:
    report = verify_store(root)
    assert report.problems == [], report.problems[:5]
    assert report.images > 0


def assert_same_weights(a: Path, b: Path) -> None:
    wa, wb = load_file(str(a)), load_file(str(b))
    assert wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), f"{a.name}: tensor {k} differs"


def history(folder: Path, file: str = "train.json") -> list[dict]:
    return strip(json.loads((folder / file).read_text())["history"])


# ---- dataset ---------------------------------------------------------------------------------

def test_dataset_killed_at_random_moments(tiny_store, tmp_path, capsys):
    reference, _ = tiny_store
    rng = random.Random(KILL_SEED)
    root = tmp_path / "killed"
    args = ["dataset", "--config", str(TINY), f"store={root}", "--quiet"]
    n_img, n_frames = rng.randint(8, 16), rng.randint(3, 4)
    points = [
        ("an EXR half-written (.exr.*.tmp appears)", lambda t: count(root, ".*.exr.*.tmp")() > 0, rng.uniform(0, 0.01)),
        (f"{n_img} EXRs written", lambda t: count(root, "*.exr")() >= n_img, rng.uniform(0, 0.2)),
        (f"{n_frames} frames complete", lambda t: count(root, "frame.json")() >= n_frames, rng.uniform(0, 0.2)),
    ]
    results = kill_series("dataset", args, points, capsys)
    assert results.count("killed") == len(points), results
    interrupted = verify_store(root)
    assert interrupted.incomplete > 0 and interrupted.problems     # verify sees the damage
    cli(*args[:-1], "--quiet")
    assert not list(root.rglob("*.tmp"))
    assert_same_store(reference, root)
    assert_same_manifests(reference, root)
    assert_verified(root)


# ---- gt-clean --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cleaned(tiny_store, tmp_path_factory):
    """The tiny store after an uninterrupted gt-clean: the reference, and the baselines' input."""
    reference, _ = tiny_store
    base = tmp_path_factory.mktemp("cleaned")
    store, runs = base / "store", base / "runs"
    shutil.copytree(reference, store)
    cli("gt-clean", "--config", TINY, f"store={store}", f"runs={runs}", *CLEAN_TINY, "--quiet")
    return store, runs


def test_gt_clean_killed_at_random_moments(tiny_store, cleaned, tmp_path, capsys):
    reference, _ = tiny_store
    ref_store, ref_runs = cleaned
    rng = random.Random(KILL_SEED + 1)
    store, runs = tmp_path / "store", tmp_path / "runs"
    shutil.copytree(reference, store)
    args = ["gt-clean", "--config", str(TINY), f"store={store}", f"runs={runs}", *CLEAN_TINY, "--quiet"]
    done = epochs_done(runs / "cleaner")
    e1, e2, n = rng.randint(1, 2), rng.randint(3, 4), rng.randint(1, 3)
    points = [
        (f"cleaner epoch {e1} done", lambda t: done() >= e1, rng.uniform(0, 0.5)),
        (f"cleaner epoch {e2} done", lambda t: done() >= e2, rng.uniform(0, 0.5)),
        (f"{n} gt_clean images written", lambda t: count(store, "gt_clean.exr")() >= n, rng.uniform(0, 0.05)),
    ]
    results = kill_series("gt-clean", args, points, capsys)
    assert results.count("killed") == len(points), results
    cli(*args)
    folder, ref_folder = runs / "cleaner", ref_runs / "cleaner"
    assert history(folder) == history(ref_folder)
    assert_same_weights(folder / "last.safetensors", ref_folder / "last.safetensors")
    assert (folder / "model.safetensors").read_bytes() == (ref_folder / "model.safetensors").read_bytes()
    clean = sorted(p.relative_to(store) for p in store.rglob("gt_clean.exr"))
    assert clean == sorted(p.relative_to(ref_store) for p in ref_store.rglob("gt_clean.exr")) and clean
    for rel in clean:
        pa, pb = exr_payload(store / rel), exr_payload(ref_store / rel)
        assert pa["record"] == pb["record"], rel
        for ch in pa["channels"]:
            assert (pa["channels"][ch] == pb["channels"][ch]).all(), f"{rel}:{ch}"
    assert strip(json.loads((store / "cleaner.json").read_text())) == strip(json.loads((ref_store / "cleaner.json").read_text()))
    assert_verified(store)


# ---- training --------------------------------------------------------------------------------

@dataclass
class TrainCase:
    """How to train one model and where its run writes (``runs/<folder>``).

    The run folder must hold ``checkpoint`` (written atomically after every epoch, safetensors,
    metadata ``state`` JSON with ``epoch``), ``best`` (the best weights) and ``history_file``
    (``{"history": [...]}``, one entry per epoch); entries' ``seconds`` are ignored.
    """
    model: str
    spp: int
    folder: str
    overrides: list = field(default_factory=list)
    checkpoint: str = "last.safetensors"
    best: str = "model.safetensors"
    history_file: str = "train.json"


TRAIN_CASES = [
    pytest.param(TrainCase("isik", 4, "isik_spp4", CLEAN_TINY), id="isik"),
    # pytest.param(TrainCase("diffusion", 4, "diffusion_spp4", [...tiny diffusion overrides...]), id="diffusion"),
]


@pytest.mark.parametrize("case", TRAIN_CASES)
def test_training_killed_resumes_with_the_same_trajectory(case, cleaned, tmp_path, capsys):
    store, _ = cleaned
    rng = random.Random(KILL_SEED + 2)
    ref_runs, runs = tmp_path / "ref", tmp_path / "killed"
    base = ["train", "--model", case.model, "--spp", str(case.spp), "--config", str(TINY), f"store={store}",
            *case.overrides]
    cli(*base, f"runs={ref_runs}", "--quiet")
    ref = ref_runs / case.folder
    epochs = len(history(ref, case.history_file))
    assert epochs >= 4
    done = epochs_done(runs / case.folder, case.checkpoint)
    e1, e2 = rng.randint(1, epochs // 2), rng.randint(epochs // 2 + 1, epochs - 1)
    t_kill = rng.uniform(1.0, 4.0)
    points = [
        (f"{t_kill:.1f} s after start", lambda t: t >= t_kill, 0.0),
        (f"epoch {e1} done", lambda t: done() >= e1, rng.uniform(0, 0.5)),
        (f"epoch {e2} done", lambda t: done() >= e2, rng.uniform(0, 0.5)),
    ]
    results = kill_series(f"train {case.model}", base + [f"runs={runs}", "--quiet"], points, capsys)
    assert results.count("killed") == len(points), results
    cli(*base, f"runs={runs}", "--quiet")
    got = runs / case.folder
    assert history(got, case.history_file) == history(ref, case.history_file)
    assert_same_weights(got / case.checkpoint, ref / case.checkpoint)
    assert (got / case.best).read_bytes() == (ref / case.best).read_bytes()


# ---- a worker process killed mid-frame ----------------------------------------------------------

# One scene, two frames, GT at 2048 spp: a frame takes seconds, so a worker can be caught
# between its first image and its frame.json.
SLOW = ["dataset.scenes=1", "dataset.gt_spp=2048"]


@pytest.fixture(scope="module")
def slow_reference(tmp_path_factory):
    root = tmp_path_factory.mktemp("slow") / "store"
    cli("dataset", "--config", TINY, f"store={root}", *SLOW, "--quiet")
    return root


WORKER_MARKS = {"local": lambda cmd: "spawn_main" in cmd,
                "ray": lambda cmd: cmd.startswith("ray::_render_frame_entry")}


@pytest.mark.parametrize("kind", ["local", "ray"])
def test_worker_killed_mid_frame_is_retried(kind, slow_reference, tmp_path, capsys):
    root = tmp_path / "store"
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "dataset", "--config", str(TINY), f"store={root}",
                             *SLOW, f"executor.kind={kind}", "executor.workers=1", "--quiet"],
                            cwd=ROOT, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    killed = None
    deadline = time.time() + 300
    while proc.poll() is None and time.time() < deadline and killed is None:
        started = [p.parent for p in root.rglob("gt1.exr") if not (p.parent / "frame.json").exists()]
        if started:
            workers = [pid for pid, cmd in session_processes(proc.pid).items() if WORKER_MARKS[kind](cmd)]
            if workers:
                os.kill(workers[0], signal.SIGKILL)
                killed = (started[0], workers[0])
        time.sleep(0.01)
    out, _ = proc.communicate(timeout=300)
    with capsys.disabled():
        print(f"\n{kind} worker: killed pid {killed and killed[1]} while rendering {killed and killed[0].name}; exit {proc.returncode}", end="")
    assert killed is not None, f"no worker caught mid-frame:\n{out}"
    assert proc.returncode == 0, out
    frame = json.loads((killed[0] / "frame.json").read_text())
    assert frame["reused_images"] >= 1        # the retried task resumed from the images written
    assert_same_store(slow_reference, root)
    assert_verified(root)
