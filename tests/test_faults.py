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
- ``train --model M`` (isik, afgsa with its critic, diffusion): resumed from the last checkpoint
  with the same per-epoch losses and bitwise-equal final weights. ``TRAIN_CASES`` lists the models: the diffusion trainer joins by
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

from mcdenoise.pipeline.verify import verify_store
from tests.helpers import CLEAN_TINY, TIMING_KEYS, TINY, all_keys, assert_same_store, cli, exr_payload

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
                capsys, probe: Callable[[], str] | None = None) -> list[str]:
    """Run ``args`` once per kill point; ``probe()`` describes what each kill left behind."""
    results = []
    for label, ready, delay in points:
        results.append(run_and_kill(args, ready, delay))
        with capsys.disabled():
            print(f"\n{name}: kill at {label} + {delay:.2f} s: {results[-1]}"
                  + (f"; left {probe()}" if probe else ""), end="")
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
    n_img, n_frames = rng.randint(4, 12), rng.randint(1, 2)
    # The last kill must leave a frame unfinished for verify to find: at most all frames but one
    # complete (the kills before it may already have let all but one finish).
    last = count(reference, "frame.json")() - 1
    points = [
        ("an EXR half-written (.exr.*.tmp appears)", lambda t: count(root, ".*.exr.*.tmp")() > 0, rng.uniform(0, 0.01)),
        (f"{n_img} more EXRs written", more(count(root, "*.exr"), n_img), rng.uniform(0, 0.2)),
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
    e1, n = rng.randint(1, 2), rng.randint(1, 3)
    points = [
        (f"{e1} cleaner epochs done", more(done, e1), rng.uniform(0, 0.5)),
        ("1 more cleaner epoch done", more(done, 1), rng.uniform(0, 0.5)),
        (f"{n} gt_clean images written", more(count(store, "gt_clean.exr"), n), rng.uniform(0, 0.05)),
    ]
    left = lambda: f"{epochs_done(runs / 'cleaner')()} epochs in last.safetensors, {count(store, 'gt_clean.exr')()} gt_clean"
    results = kill_series("gt-clean", args, points, capsys, probe=left)
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
    spp: int | str
    folder: str
    overrides: list = field(default_factory=list)
    checkpoint: str = "last.safetensors"
    best: str = "model.safetensors"
    history_file: str = "train.json"


TRAIN_CASES = [
    pytest.param(TrainCase("isik", 4, "isik_spp4", CLEAN_TINY + ["clean.epochs=8"]), id="isik"),
    pytest.param(TrainCase("afgsa", 4, "afgsa_spp4", AFGSA_TINY), id="afgsa"),
    pytest.param(TrainCase("oidn_ft", "any", "oidn_ft_rt_hdr_alb_nrm",
                           ["oidn_ft.epochs=5", "oidn_ft.crop=16", "oidn_ft.batch_size=2", "oidn_ft.crops_per_frame=2",
                            "oidn_ft.distill=0.5", "oidn_ft.l2sp=0.1", "oidn_ft.device=cpu"]), id="oidn_ft"),
    pytest.param(TrainCase("diffusion", 4, "diffusion_spp4",
                           ["diffusion.epochs=4", "diffusion.crop=16", "diffusion.batch_size=2",
                            "diffusion.val_frames=1", "diffusion.warmup_steps=2", "diffusion.device=cpu",
                            "diffusion.base_network=rt_hdr_alb_nrm"],   # the EMA state resumes too
                           best="control.safetensors"), id="diffusion"),
]


@pytest.mark.parametrize("case", TRAIN_CASES)
def test_training_killed_resumes_with_the_same_trajectory(case, cleaned, tmp_path, capsys):
    store, _ = cleaned
    rng = random.Random(KILL_SEED + 2)
    ref_runs, runs = tmp_path / "ref", tmp_path / "killed"
    base = ["train", "--model", case.model, "--spp", str(case.spp), "--config", str(TINY), f"store={store}",
            *case.overrides]
    t0 = time.time()
    cli(*base, f"runs={ref_runs}", "--quiet")
    t_ref = time.time() - t0
    ref = ref_runs / case.folder
    epochs = len(history(ref, case.history_file))
    assert epochs >= 4
    done = epochs_done(runs / case.folder, case.checkpoint)
    e1 = rng.randint(1, epochs // 2)
    # A fraction of the reference run's time, not fixed seconds: on a quiet machine the tiny runs
    # finished most epochs within 3 s, and the later kill points then found nothing left to kill.
    t_kill = rng.uniform(0.1, 0.3) * t_ref
    points = [
        (f"{t_kill:.1f} s after start", lambda t: t >= t_kill, 0.0),
        (f"{e1} epochs done", more(done, e1), rng.uniform(0, 0.5)),
        ("1 more epoch done", more(done, 1), rng.uniform(0, 0.5)),
    ]
    results = kill_series(f"train {case.model}", base + [f"runs={runs}", "--quiet"], points, capsys,
                          probe=lambda: f"{done()} epochs in {case.checkpoint}")
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
    from mcdenoise.pipeline import checkpoint, schema
    from mcdenoise.pipeline.store import Store

    store = Store(tmp_path / "store")
    store.write_manifest({"scenes": [], "splits": {}})
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    _fail_mid_write(monkeypatch)
    monkeypatch.setattr(checkpoint, "atomic_write_bytes", exr.atomic_write_bytes)
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
            checkpoint.save_safetensors(target, {"w": torch.ones(3)}, {"format": "x"})
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
    from mcdenoise.clean.cli import cmd_gt_clean
    from mcdenoise.clean.train import run_dir
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
