"""Fault injection: SIGKILL the stages at seeded random moments, rerun, compare with an
uninterrupted run. Five kill points per stage; each stage's list is printed as it runs and, for the
stages whose rerun came out identical, at the end of the run (``tests/conftest.py``).

Kill points come from progress markers (files appearing in the store or the run folder, the
epoch recorded in ``last.safetensors``) plus a seeded random delay, not from bare sleeps, so
they land at the intended stage on a slow or a busy machine. Every killed run is SIGKILLed with
its whole process group (worker processes too), then the same command is rerun to completion:

- ``dataset``: EXR pixels and header records identical to the uninterrupted run (headers carry
  wall-clock ``render_seconds``, so files are compared channel by channel, not byte by byte),
  manifests identical but for timings, ``verify`` clean;
- ``gt-clean``: the cleaner's final weights and optimizer state bitwise equal, the same loss
  history, identical gt_clean images and cleaner.json;
- ``train --model M`` (isik, afgsa with its critic, oidn_ft, and diffusion: the Control Module on
  OIDN's frozen network): resumed from the last checkpoint with the
  same per-epoch losses and bitwise-equal final weights. ``TRAIN_CASES`` lists the models: another
  trainer joins by adding one ``TrainCase``;
- ``eval`` and ``export``, whose writes all come within milliseconds: killed from inside, just
  before a file-system event (``tests/killhook.py``: a file opened for writing, a rename, a folder
  removal), five events drawn from the run's list, its last (the commit point) always; the report's
  numbers and images, and the exported model folder byte for byte, equal the uninterrupted run's;
- a worker process killed mid-frame (local pool and Ray): the task is retried, resumes from the
  images already written, and the dataset completes identical to the reference;
- full disk (RLIMIT_FSIZE, or ENOSPC injected mid-write) and read-only folders: one line naming
  the file, a non-zero exit, no partial or temporary file (dataset, writers of images, manifests
  and checkpoints, eval, export).
"""
from __future__ import annotations

import csv
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

from mcdenoise.pipeline.verify import verify_store
from tests.helpers import CLEAN_TINY, KILL_POINTS, TIMING_KEYS, TINY, all_keys, assert_same_store, cli, exr_payload

pytestmark = pytest.mark.slow   # subprocesses killed and rerun: make test runs them, make test-fast does not

ROOT = Path(__file__).resolve().parents[1]
KILL_SEED = 20261122
AFGSA_TINY = ["afgsa.epochs=8", "afgsa.batch_size=4", "afgsa.crop=16", "afgsa.crops_per_frame=8",
              "afgsa.channels=8", "afgsa.extractor_channels=4", "afgsa.blocks=1", "afgsa.block_size=4",
              "afgsa.halo=1", "afgsa.critic_channels=4", "afgsa.critic_levels=2", "afgsa.device=cpu"]
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


def run_and_kill(args: list[str], ready: Callable[[float], bool], delay: float, timeout: float = 300,
                 urgent: Callable[[], bool] | None = None) -> str:
    """Start ``python -m pipeline ARGS``, SIGKILL its process group ``delay`` s after
    ``ready(seconds since start)`` is true, or as soon as ``urgent()`` is (the run is about to finish).

    Returns how it ended: 'killed' or 'finished first' (the marker never came before exit).
    """
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", *args], cwd=ROOT, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    start = time.time()
    try:
        while proc.poll() is None and time.time() < start + timeout:
            if ready(time.time() - start):
                end = time.time() + delay
                while time.time() < end and not (urgent and urgent()):
                    time.sleep(0.005)
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


def more(counter: Callable[[], int], n: int, cap: int | None = None) -> Callable[[float], bool]:
    """A kill marker: ``counter`` grew by ``n`` since this run started (the store may already
    hold progress from a previous, killed run), or reached ``cap``, so that a kill can be made to
    land while the work is still unfinished however far the previous kills let it get."""
    base: list[int] = []

    def ready(_t: float) -> bool:
        if not base:
            base.append(counter())
        now = counter()
        return now - base[0] >= n or (cap is not None and now >= cap)
    return ready


def epochs_done(folder: Path, checkpoint: str = "last.safetensors") -> Callable[[], int]:
    def read() -> int:
        try:
            with safe_open(str(folder / checkpoint), framework="pt") as f:
                return int(json.loads(f.metadata()["state"])["epoch"])
        except Exception:  # noqa: BLE001 - not there yet, or replaced while we looked
            return 0
    return read


def kill_series(name: str, args: list[str], points: list[tuple[str, Callable[[float], bool], float]],
                capsys, probe: Callable[[], str] | None = None, urgent: Callable[[], bool] | None = None) -> list[str]:
    """Run ``args`` once per kill point; ``probe()`` describes what each kill left behind."""
    results, lines = [], []
    for label, ready, delay in points:
        results.append(run_and_kill(args, ready, delay, urgent=urgent))
        lines.append(f"kill at {label} + {delay:.2f} s: {results[-1]}" + (f"; left {probe()}" if probe else ""))
        with capsys.disabled():
            print(f"\n{name}: {lines[-1]}", end="")
    LANDED[name] = lines
    return results


# stage -> how its kills landed; ``identical(stage)`` reports them once the rerun matched the reference.
LANDED: dict[str, list[str]] = {}


def identical(name: str) -> None:
    KILL_POINTS[name] = LANDED.pop(name)


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
        if rel.name == "dataset.json":     # where the stores and their runs are, not what they hold
            for key in ("store", "runs"):
                ja["config"].pop(key), jb["config"].pop(key)
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
    n_img, n_gt2, n_frames = rng.randint(4, 12), rng.randint(1, 2), rng.randint(1, 2)
    # The last kill must leave a frame unfinished for verify to find: at most all frames but one
    # complete (the kills before it may already have let all but one finish).
    last = count(reference, "frame.json")() - 1
    points = [
        ("the store's dataset.json written", lambda t: count(root, "dataset.json")() > 0, rng.uniform(0, 0.05)),
        ("an EXR half-written (.exr.*.tmp appears)", lambda t: count(root, ".*.exr.*.tmp")() > 0, rng.uniform(0, 0.01)),
        (f"{n_img} more EXRs written", more(count(root, "*.exr"), n_img), rng.uniform(0, 0.2)),
        (f"{n_gt2} more GT2 images written", more(count(root, "gt2.exr"), n_gt2), rng.uniform(0, 0.2)),
        (f"{n_frames} more frames complete (at most {last})", more(count(root, "frame.json"), n_frames, cap=last),
         rng.uniform(0, 0.2)),
    ]
    left = lambda: (f"{count(root, '*.exr')()} EXRs, {count(root, 'frame.json')()} frames, "
                    f"{count(root, '*.tmp')()} temporary files")
    results = kill_series("dataset", args, points, capsys, probe=left)
    assert results.count("killed") == len(points), results
    interrupted = verify_store(root)
    assert interrupted.incomplete > 0 and interrupted.problems     # verify sees the damage
    cli(*args[:-1], "--quiet")
    assert not list(root.rglob("*.tmp"))
    assert_same_store(reference, root)
    assert_same_manifests(reference, root)
    assert_verified(root)
    identical("dataset")


def test_killing_the_dataset_process_alone_stops_its_workers(tmp_path):
    """``kill PID`` of a run (not its process group): its render workers die with it, no orphan renders on."""
    root = tmp_path / "store"
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "dataset", "--config", str(TINY), f"store={root}",
                             "executor.workers=2", "--quiet"], cwd=ROOT, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and count(root, "*.exr")() == 0:    # the workers are rendering
            time.sleep(0.05)
        workers = set(session_processes(proc.pid)) - {proc.pid}
        assert workers, "no worker processes seen"
        proc.kill()
        proc.wait()
        deadline = time.time() + 30
        while time.time() < deadline and set(session_processes(proc.pid)) & workers:
            time.sleep(0.1)
        assert not set(session_processes(proc.pid)) & workers, session_processes(proc.pid)
    finally:
        for pid in session_processes(proc.pid):
            os.kill(pid, signal.SIGKILL)


# ---- gt-clean --------------------------------------------------------------------------------

def test_gt_clean_killed_at_random_moments(tiny_store, cleaned, tmp_path, capsys):
    reference, _ = tiny_store
    ref_store, ref_runs = cleaned
    rng = random.Random(KILL_SEED + 1)
    store, runs = tmp_path / "store", tmp_path / "runs"
    shutil.copytree(reference, store)
    args = ["gt-clean", "--config", str(TINY), f"store={store}", f"runs={runs}", *CLEAN_TINY, "--quiet"]
    done = epochs_done(runs / "cleaner")
    # 5 epochs (CLEAN_TINY), 6 frames: the epoch kills stop at 4 epochs at most, the image kills at 3 images
    e1, n = rng.randint(1, 2), rng.randint(1, 2)
    points = [
        (f"{e1} cleaner epochs done", more(done, e1), rng.uniform(0, 0.5)),
        ("1 more cleaner epoch done", more(done, 1), rng.uniform(0, 0.5)),
    ]
    left = lambda: f"{epochs_done(runs / 'cleaner')()} epochs in last.safetensors, {count(store, 'gt_clean.exr')()} gt_clean"
    results = kill_series("gt-clean", args, points, capsys, probe=left)
    assert results.count("killed") == len(points), results
    # The gt_clean images come within milliseconds of each other, too fast to be killed between from outside:
    # the kill comes from inside (tests/killhook.py), just before the n-th image appears, then one later.
    spare, spare_runs = tmp_path / "events_store", tmp_path / "events_runs"
    shutil.copytree(reference, spare)
    log = tmp_path / "gt-clean.events"
    spare_args = [a.replace(str(store), str(spare)).replace(str(runs), str(spare_runs)) for a in args]
    assert run_hooked(spare_args, spare, events=log) == "finished first"
    # an image appears by renaming its finished temporary file (OpenEXR writes that file itself)
    writes = [e for e in log.read_text().splitlines() if e.startswith("rename ") and e.endswith("gt_clean.exr")]
    assert len(writes) >= n + 2, writes
    for k in (n, rng.randint(n + 1, len(writes) - 1), len(writes)):
        result = run_hooked(args, store, kill=(writes[k - 1], 1))
        LANDED["gt-clean"].append(f"kill before gt_clean image {k}/{len(writes)} appears: {result}; left {left()}")
        with capsys.disabled():
            print(f"\ngt-clean: {LANDED['gt-clean'][-1]}", end="")
        assert result == "killed", LANDED["gt-clean"][-1]
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
    identical("gt-clean")


# ---- training --------------------------------------------------------------------------------

@dataclass
class TrainCase:
    """How to train one model and where its run writes (``runs/<folder>``).

    The run folder must hold ``checkpoint`` (written atomically after every epoch, safetensors,
    metadata ``state`` JSON with ``epoch``), ``best`` (the best weights) and ``history_file``
    (``{"history": [...]}``, one entry per epoch); entries' ``seconds`` are ignored.
    """
    model: str
    spp: int | str
    folder: str
    overrides: list = field(default_factory=list)
    checkpoint: str = "last.safetensors"
    best: str = "model.safetensors"
    history_file: str = "train.json"


# The Control Module on OIDN's frozen network (train/train.py train); the EMA state resumes too.
REFINE = TrainCase("diffusion", 4, "diffusion_spp4",
                   ["diffusion.epochs=4", "diffusion.crop=16", "diffusion.batch_size=2", "diffusion.val_frames=1",
                    "diffusion.warmup_steps=2", "diffusion.device=cpu", "diffusion.base_network=rt_hdr_alb_nrm"],
                   best="control.safetensors")
TRAIN_CASES = [
    pytest.param(TrainCase("isik", 4, "isik_spp4", CLEAN_TINY + ["clean.epochs=8"]), id="isik"),
    pytest.param(TrainCase("afgsa", 4, "afgsa_spp4", AFGSA_TINY), id="afgsa"),
    pytest.param(TrainCase("oidn_ft", "any", "oidn_ft_rt_hdr_alb_nrm",
                           ["oidn_ft.epochs=5", "oidn_ft.crop=16", "oidn_ft.batch_size=2", "oidn_ft.crops_per_frame=2",
                            "oidn_ft.distill=0.5", "oidn_ft.l2sp=0.1", "oidn_ft.device=cpu"]), id="oidn_ft"),
    pytest.param(REFINE, id="diffusion"),
]


def train_args(case: TrainCase, store: Path) -> list[str]:
    return ["train", "--model", case.model, "--spp", str(case.spp), "--config", str(TINY), f"store={store}",
            *case.overrides]


@pytest.fixture(scope="module")
def reference_runs(cleaned, tmp_path_factory):
    """``get(case)``: (run folder, seconds) of an uninterrupted run of ``case``, trained on first use, so
    that the export test reuses the training test's reference."""
    store, _ = cleaned
    root, done = tmp_path_factory.mktemp("reference_runs"), {}

    def get(case: TrainCase) -> tuple[Path, float]:
        key = repr(case)
        if key not in done:
            runs = root / str(len(done))
            t0 = time.time()
            cli(*train_args(case, store), f"runs={runs}", "--quiet")
            done[key] = (runs / case.folder, time.time() - t0)
        return done[key]
    return get


@pytest.mark.parametrize("case", TRAIN_CASES)
def test_training_killed_resumes_with_the_same_trajectory(case, cleaned, reference_runs, tmp_path, capsys, request):
    store, _ = cleaned
    rng = random.Random(KILL_SEED + 2)
    runs = tmp_path / "killed"
    base = train_args(case, store)
    ref, t_ref = reference_runs(case)
    epochs = epochs_done(ref, case.checkpoint)()      # the last checkpoint's epoch
    assert epochs >= 4
    done = epochs_done(runs / case.folder, case.checkpoint)
    e1 = rng.randint(1, epochs // 2)
    # A fraction of the reference run's time, not fixed seconds: on a quiet machine the tiny runs
    # finished most epochs within 3 s, and the later kill points then found nothing left to kill.
    t_kill = rng.uniform(0.1, 0.3) * t_ref
    # The second timed kill lands early in a rerun: while it loads the checkpoint or in the epoch after.
    # The last epoch kills are capped at all epochs but one, so that each still finds a run to kill.
    t_resume = rng.uniform(0.05, 0.15) * t_ref
    # Every point also fires, without its delay, once all epochs but one are done, so that a slow
    # reference (a loaded machine) or kills that let the run get far cannot make a point miss the run.
    last = epochs - 1
    points = [
        (f"{t_kill:.1f} s after start (or {last} epochs done)", lambda t: t >= t_kill or done() >= last, 0.0),
        (f"{e1} epochs done (at most {last})", more(done, e1, cap=last), rng.uniform(0, 0.5)),
        (f"1 more epoch done (at most {last})", more(done, 1, cap=last), rng.uniform(0, 0.5)),
        (f"{t_resume:.1f} s after start (or {last} epochs done)", lambda t: t >= t_resume or done() >= last, 0.0),
        (f"1 more epoch done (at most {last})", more(done, 1, cap=last), rng.uniform(0, 0.5)),
    ]
    name = f"train {request.node.callspec.id}"
    results = kill_series(name, base + [f"runs={runs}", "--quiet"], points, capsys,
                          probe=lambda: f"{done()} epochs in {case.checkpoint}", urgent=lambda: done() >= last)
    assert results.count("killed") == len(points), results
    cli(*base, f"runs={runs}", "--quiet")
    got = runs / case.folder
    assert history(got, case.history_file) == history(ref, case.history_file)
    assert_same_weights(got / case.checkpoint, ref / case.checkpoint)
    assert (got / case.best).read_bytes() == (ref / case.best).read_bytes()
    identical(name)


# ---- eval and export: killed at their file-system events ---------------------------------------------
# Their writes come within milliseconds of each other, after seconds of start-up and computing: the
# kill comes from inside the process (tests/killhook.py), just before its N-th file opened for writing,
# renamed or removed in the output folder. Every such moment of a run is a possible kill point; five are
# drawn, the stage's commit point (the last event) always among them.

def run_hooked(args: list[str], under: Path, events: Path | None = None, kill: tuple[str, int] | None = None) -> str:
    """``python -m pipeline ARGS`` under tests/killhook.py: list its events in ``events``, or SIGKILL it at
    ``kill`` (an event's name and occurrence)."""
    env = {**os.environ, "KILL_UNDER": str(under)}
    if events is not None:
        env["EVENTS_FILE"] = str(events)
    if kill is not None:
        env["KILL_EVENT"], env["KILL_OCCURRENCE"] = kill[0], str(kill[1])
    proc = subprocess.run([sys.executable, "-m", "tests.killhook", *map(str, args)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    if proc.returncode == -signal.SIGKILL:
        return "killed"
    assert proc.returncode == 0, proc.stderr
    return "finished first"


def kill_at_events(name: str, args: list[str], out: Path, prepare: Callable[[], None], rng: random.Random,
                   capsys, each: Callable[[Path], None] | None = None) -> Path:
    """``prepare()`` the folder of ``out``; the reference run ``args --out OUT``, listing its events, is moved
    aside and returned (``out`` is named in what it writes); then a run killed before each of five of the
    events, in their order, the last (the stage's commit point) included: one after the other from one
    ``prepare()``, or with ``each(reference)``, each from a new ``prepare()`` and followed by a rerun and
    ``each`` (where what a kill leaves changes the events of the next run)."""
    folder = out.parent
    prepare()
    log = folder.parent / f"{name}.events"
    assert run_hooked([*args, "--out", out], folder, events=log) == "finished first"
    events = log.read_text().splitlines()
    assert len(events) >= 5, events
    reference = folder.parent / f"{name}.reference"
    folder.rename(reference)
    prepare()
    points = sorted(rng.sample(range(1, len(events)), 4)) + [len(events)]
    lines = []
    for k in points:
        if each is not None and k != points[0]:
            shutil.rmtree(folder)
            prepare()
        kill = (events[k - 1], events[:k].count(events[k - 1]))
        result = run_hooked([*args, "--out", out], folder, kill=kill)
        lines.append(f"kill before event {k}/{len(events)} ({kill[0]}): {result}")
        with capsys.disabled():
            print(f"\n{name}: {lines[-1]}", end="")
        assert result == "killed", lines[-1]
        if each is not None:
            cli(*args, "--out", out)
            each(reference)
    LANDED[name] = lines
    return reference


EVAL_TINY = ["eval.methods=[noisy, oidn, oidn_color]", "eval.spp=[4, 16]", "eval.metrics=[l1, psnr, ssim]",
             "eval.equal_time=none", "eval.device=cpu"]


def report_payload(folder: Path) -> dict:
    """A report's numbers without wall-clock times: eval.json and the CSVs without timing fields, the
    PNGs of images (crops, per-scene bars) byte for byte; the error-vs-time plot and eval.md show times."""
    out = {"files": sorted(p.name for p in folder.iterdir()),
           "eval.json": strip({k: v for k, v in json.loads((folder / "eval.json").read_text()).items()}),
           "png": {p.name: p.read_bytes() for p in folder.glob("*.png") if not p.name.startswith("error_vs_time")}}
    out["eval.json"]["meta"].pop("date")
    for p in folder.glob("*.csv"):
        rows = list(csv.reader(p.read_text().splitlines()))
        keep = [i for i, h in enumerate(rows[0]) if "seconds" not in h]
        out[p.name] = [[r[i] for i in keep] for r in rows]
    return out


def test_eval_killed_at_its_writes(cleaned, tmp_path, capsys):
    store, runs = cleaned
    rng = random.Random(KILL_SEED + 3)
    args = ["eval", "--config", TINY, f"store={store}", f"runs={runs}", *EVAL_TINY, "--quiet"]
    out = tmp_path / "reports" / "tiny"
    ref = kill_at_events("eval", args, out, lambda: out.parent.mkdir(), rng, capsys)
    cli(*args, "--out", out)
    assert report_payload(out) == report_payload(ref / out.name)
    identical("eval")


def test_export_killed_at_its_writes(reference_runs, cleaned, tmp_path, capsys, monkeypatch):
    """``export`` of the Control Module on OIDN into a model folder that already holds an ``oidn_ft/``
    folder (which the export keeps): after each kill the rerun gives the same folder, ``oidn_ft/`` too.
    The export date is pinned (SOURCE_DATE_EPOCH), as the runs may straddle midnight."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1764892800")      # the subprocesses inherit it
    store, _ = cleaned
    run, _ = reference_runs(REFINE)
    rng = random.Random(KILL_SEED + 4)
    args = ["export", "--spp", "4", "--config", TINY, f"store={store}", f"runs={run.parent}", *REFINE.overrides,
            "--quiet"]
    out = tmp_path / "models" / "model"

    def prepare():
        (out / "oidn_ft").mkdir(parents=True)
        (out / "oidn_ft" / "rt_hdr.json").write_text('{"kept": true}')

    def same(reference: Path) -> None:
        files = lambda root: {p.relative_to(root): p.read_bytes() for p in root.rglob("*") if p.is_file()}
        assert files(out.parent) == files(reference)    # nothing else beside the folder either (no .tmp, no .old)
    kill_at_events("export", args, out, prepare, rng, capsys, each=same)
    identical("export")


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
                "ray": lambda cmd: cmd.startswith("ray::render_frame_entry")}


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
        print(f"\n{kind} worker: killed pid {killed and killed[1]} while rendering {killed and killed[0].name}; "
              f"exit {proc.returncode}", end="")
    assert killed is not None, f"no worker caught mid-frame:\n{out}"
    assert proc.returncode == 0, out
    frame = json.loads((killed[0] / "frame.json").read_text())
    assert frame["reused_images"] >= 1        # the retried task resumed from the images written
    assert_same_store(slow_reference, root)
    assert_verified(root)


# ---- full disk, read-only store -------------------------------------------------------------------

def _fail_mid_write(monkeypatch, err: int = 28):
    """Make every atomic write fail half-way: the writer writes some bytes, then the OS says ENOSPC."""
    import mcdenoise.pipeline.exr as exr

    real = exr.atomic_write_bytes

    def failing(path, writer):
        def half(tmp):
            writer(tmp)
            with open(tmp, "r+b") as f:
                f.truncate(max(1, os.path.getsize(tmp) // 2))
            raise OSError(err, os.strerror(err), tmp)
        return real(path, half)

    monkeypatch.setattr(exr, "atomic_write_bytes", failing)


@pytest.mark.parametrize("what", ["image", "manifest", "checkpoint"])
def test_disk_full_mid_write_leaves_nothing(what, tmp_path, monkeypatch):
    import numpy as np

    import mcdenoise.pipeline.exr as exr
    from mcdenoise.pipeline import schema, weights
    from mcdenoise.pipeline.store import Store
    from mcdenoise.pipeline.weights import save_safetensors

    store = Store(tmp_path / "store")
    store.write_manifest({"scenes": [], "splits": {}})
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    _fail_mid_write(monkeypatch)
    monkeypatch.setattr(weights, "atomic_write_bytes", exr.atomic_write_bytes)
    arrays = {k: np.ones((4, 5, schema.BY_NAME[k.removesuffix(".variance")].size), np.float32) for k in all_keys()}
    target = {"image": tmp_path / "store/scenes/s0/000/gt1.exr", "manifest": store.manifest_path,
              "checkpoint": tmp_path / "runs/last.safetensors"}[what]
    with pytest.raises(exr.StoreWriteError, match=rf"{target.name}: writing failed, nothing was written "
                                                  r"\(No space left on device: the disk is full\)"):
        if what == "image":
            store.write_image("s0", 0, "gt1", arrays)
        elif what == "manifest":
            store.write_manifest({"scenes": ["s0"], "splits": {"train": ["s0"]}})
        else:
            save_safetensors(target, {"w": torch.ones(3)}, {"format": "x"})
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before            # the old manifest intact, no partial or temporary file


def _limit_file_size(limit: int):
    def preexec():
        import resource
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return preexec


def test_dataset_on_a_full_disk_fails_clearly_and_writes_no_partial_file(tmp_path):
    """A real file-system refusal: RLIMIT_FSIZE makes every write past 40 kB fail (EFBIG), as a
    full disk would, in the CLI and its worker processes. Manifests fit, images do not."""
    root = tmp_path / "store"
    # drjit's kernel cache (~/.drjit) would hit the limit too: give this run its own.
    env = {**os.environ, "HOME": str(tmp_path / "home")}
    proc = subprocess.run([sys.executable, "-m", "pipeline", "dataset", "--config", str(TINY), f"store={root}",
                           "dataset.scenes=1", "dataset.frames=1", "--quiet"], cwd=ROOT, capture_output=True,
                          text=True, timeout=300, preexec_fn=_limit_file_size(40_000), env=env)
    assert proc.returncode == 1, proc.stderr
    out = proc.stdout + proc.stderr
    assert f"FAILED frame s00000/000: {root}/scenes/s00000/000/gt1.exr: writing failed, nothing was written" in out
    assert "File too large" in out
    assert "Traceback" not in out
    assert not list(root.rglob("*.tmp")) and not list(root.rglob("*.exr"))
    report = verify_store(root)          # the store says what is missing, nothing is damaged
    assert report.incomplete == 1 and all("incomplete" in p for p in report.problems)


def _read_only_preexec():
    """Run a command that may not write where the permission bits say so, even as root:
    root drops CAP_DAC_OVERRIDE/CAP_DAC_READ_SEARCH from its bounding set before exec."""
    def preexec():
        if os.geteuid() == 0:
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            for cap in (1, 2):
                if libc.prctl(24, cap, 0, 0, 0) != 0:       # PR_CAPBSET_DROP
                    raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")
    return preexec


def test_read_only_store_is_a_clear_error_naming_the_path(tiny_store, tmp_path):
    reference, _ = tiny_store
    root = tmp_path / "store"
    shutil.copytree(reference, root)
    before = {p: p.stat().st_mtime_ns for p in root.rglob("*")}
    subprocess.run(["chmod", "-R", "a-w", str(root)], check=True)
    try:
        run = lambda *a: subprocess.run([sys.executable, "-m", "pipeline", *a], cwd=ROOT, capture_output=True,
                                        text=True, timeout=300, preexec_fn=_read_only_preexec())
        proc = run("dataset", "--config", str(TINY), f"store={root}", "--quiet")
        assert proc.returncode == 2, proc.stderr
        assert f"error: {root / 'dataset.json'}: cannot write into {root} (Permission denied: the store is not writable)" \
            in proc.stderr
        assert "Traceback" not in proc.stderr
        assert run("verify", str(root)).returncode == 0      # reading a read-only store is fine
    finally:
        subprocess.run(["chmod", "-R", "u+w", str(root)], check=True)
    assert {p: p.stat().st_mtime_ns for p in root.rglob("*")} == before


# ---- the training history after a kill at the last epoch's commit point ------------------------------

def test_history_is_complete_after_a_kill_right_after_the_last_checkpoint(tmp_path):
    """train.json and loss.png one epoch behind last.safetensors (what a kill between the two writes
    would leave if the history were written second) are rewritten by the rerun, which has no epoch
    left to train."""
    from mcdenoise.clean.train import run_dir, train
    from tests.helpers import make_clean_store, tiny_cfg

    make_clean_store(tmp_path / "store")
    cfg = tiny_cfg(tmp_path, epochs=2)
    train(cfg, "cleaner", quiet=True)
    folder = run_dir(cfg, "cleaner")
    full = json.loads((folder / "train.json").read_text())
    assert len(full["history"]) == 2
    # The checkpoint says 2 epochs, the history 1.
    (folder / "train.json").write_text(json.dumps({**full, "history": full["history"][:1]}))
    summary = train(cfg, "cleaner", quiet=True)
    assert summary["trained_epochs"] == 0
    assert json.loads((folder / "train.json").read_text()) == full


def test_stale_temporary_files_of_a_killed_clean_run_are_removed(tmp_path):
    """A kill mid-write leaves ``.<name>.*.tmp``; the next run of the stage removes its own."""
    from mcdenoise.clean.train import gt_clean as cmd_gt_clean, run_dir
    from mcdenoise.pipeline.store import Store
    from tests.helpers import make_clean_store, tiny_cfg

    make_clean_store(tmp_path / "store")
    cfg = tiny_cfg(tmp_path, epochs=1)
    store = Store(cfg.store)
    key = store.frames()[0]
    stale_image = store.frame_dir(key.scene, key.frame) / ".gt_clean.exr.abc123.tmp"
    stale_ckpt = run_dir(cfg, "cleaner") / ".last.safetensors.xyz789.tmp"
    for p in (stale_image, stale_ckpt):
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"half")
    assert cmd_gt_clean(cfg, quiet=True) == 0
    assert not stale_image.exists() and not stale_ckpt.exists()
    assert not list(Path(cfg.store).rglob("*.tmp"))


def _stage_args(stage: str, cleaned, reference_runs) -> list[str]:
    store, runs = cleaned
    if stage == "eval":
        return ["eval", "--config", TINY, f"store={store}", f"runs={runs}", *EVAL_TINY, "--quiet"]
    run, _ = reference_runs(REFINE)
    return ["export", "--spp", "4", "--config", TINY, f"store={store}", f"runs={run.parent}", *REFINE.overrides,
            "--quiet"]


@pytest.mark.parametrize("stage", ["eval", "export"])
def test_eval_and_export_on_a_full_disk_or_read_only_folder_fail_in_one_line(stage, cleaned, reference_runs,
                                                                              tmp_path):
    """Every write past 20 kB refused (RLIMIT_FSIZE, as a full disk would: the report's first figure, the
    model's base.tza), then an output folder that cannot be written: one line naming the file, exit 2,
    no file left, not even a temporary one."""
    args = _stage_args(stage, cleaned, reference_runs)
    run = lambda out, preexec: subprocess.run([sys.executable, "-m", "pipeline", *map(str, args), "--out", out],
                                              cwd=ROOT, capture_output=True, text=True, timeout=300,
                                              preexec_fn=preexec)
    full, locked = tmp_path / "full", tmp_path / "locked"
    locked.mkdir()
    proc = run(full / "out", _limit_file_size(20_000))
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert len(errors) == 1 and str(full / "out") in errors[0] and "File too large" in errors[0], proc.stderr
    assert not [p for p in full.rglob("*") if p.is_file()]
    subprocess.run(["chmod", "a-w", str(locked)], check=True)
    try:
        proc = run(locked / "out", _read_only_preexec())
    finally:
        subprocess.run(["chmod", "u+w", str(locked)], check=True)
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert len(errors) == 1 and str(locked / "out") in errors[0] and "Permission denied" in errors[0], proc.stderr
    assert not list(locked.rglob("*"))
