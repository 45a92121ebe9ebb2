"""Where frame tasks run: worker processes on this machine, or Ray tasks (local or a cluster).

Both executors take a list of picklable tasks and a module-level function, and yield
``(task, result, error)`` as tasks finish, so the caller owns progress and bookkeeping. No
scheduling of our own beyond that: the local one is ``concurrent.futures`` with the ``spawn``
start method, the distributed one is Ray.

Native crashes happen (Mitsuba can segfault on some inputs). Rendering in worker processes
turns such a crash into a failed task with a clear error instead of a dead run: when a worker
dies the pool is rebuilt and the tasks that were in flight are retried, up to ``retries`` times.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import sys
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Iterator

from .config import ExecutorConfig
from .errors import TaskFailed


def _die_with_parent() -> None:
    """Worker initializer (Linux): the kernel kills the worker when the process that started it dies, so a
    run killed on its own (``kill PID``, a scheduler's time limit) leaves no orphan rendering on; the frame
    it was on is not written (files appear by rename) and the next run renders it."""
    if sys.platform.startswith("linux"):
        import ctypes
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)   # 1: PR_SET_PDEATHSIG
        if os.getppid() == 1:        # the parent died before the line above
            os._exit(1)


def run_local(tasks: list, fn: Callable, cfg: ExecutorConfig) -> Iterator[tuple[Any, Any, BaseException | None]]:
    pending = list(enumerate(tasks))[::-1]   # pop() from the end keeps the original order
    crashes: dict[int, int] = {}
    ctx = multiprocessing.get_context("spawn")
    while pending:
        pool = ProcessPoolExecutor(max_workers=cfg.workers, mp_context=ctx, initializer=_die_with_parent)
        in_flight: dict = {}
        broken = False
        try:
            while pending or in_flight:
                # Keep at most `workers` tasks submitted so a crash implicates few of them.
                while pending and len(in_flight) < cfg.workers:
                    i, task = pending.pop()
                    in_flight[pool.submit(fn, task)] = (i, task)
                done, _ = wait(in_flight, return_when=FIRST_COMPLETED)
                for fut in done:
                    i, task = in_flight.pop(fut)
                    try:
                        yield task, fut.result(), None
                    except BrokenProcessPool:
                        broken = True
                        crashes[i] = crashes.get(i, 0) + 1
                        if crashes[i] > cfg.retries:
                            yield task, None, TaskFailed(
                                f"worker process died {crashes[i]} times (native crash or killed) on {task_label(task)}")
                        else:
                            pending.append((i, task))
                    except Exception as exc:  # noqa: BLE001 - reported to the caller with the task
                        yield task, None, exc
                if broken:
                    for fut, (i, task) in in_flight.items():
                        crashes[i] = crashes.get(i, 0) + 1
                        pending.append((i, task))
                    in_flight.clear()
                    break
        finally:
            pool.shutdown(wait=not broken, cancel_futures=True)


def run_ray(tasks: list, fn: Callable, cfg: ExecutorConfig) -> Iterator[tuple[Any, Any, BaseException | None]]:
    try:
        import ray
    except ImportError as exc:
        raise TaskFailed("executor.kind=ray needs the 'ray' package (pip install ray)") from exc
    started = False
    if not ray.is_initialized():
        kwargs: dict = {"ignore_reinit_error": True, "log_to_driver": False,
                        "runtime_env": {"env_vars": {k: v for k, v in os.environ.items()
                                                     if k in ("DRJIT_LIBLLVM_PATH", "PYTHONPATH")}}}
        if cfg.address:
            kwargs["address"] = cfg.address
        else:
            kwargs["num_cpus"] = max(1, int(cfg.workers * cfg.ray_cpus_per_task))
            kwargs["include_dashboard"] = False
        ray.init(**kwargs)
        started = True
    try:
        remote = ray.remote(num_cpus=cfg.ray_cpus_per_task, max_retries=cfg.retries,
                            retry_exceptions=False)(fn)
        refs = {remote.remote(task): task for task in tasks}
        while refs:
            done, _ = ray.wait(list(refs), num_returns=1)
            for ref in done:
                task = refs.pop(ref)
                try:
                    yield task, ray.get(ref), None
                except Exception as exc:  # noqa: BLE001 - RayTaskError wraps the worker's exception
                    yield task, None, exc
    finally:
        if started:
            ray.shutdown()


def run_tasks(tasks: list, fn: Callable, cfg: ExecutorConfig):
    if cfg.kind == "ray":
        return run_ray(tasks, fn, cfg)
    return run_local(tasks, fn, cfg)


def task_label(task: Any) -> str:
    scene, frame = getattr(task, "scene", None), getattr(task, "frame", None)
    return f"frame {scene}/{frame:03d}" if scene is not None and frame is not None else repr(task)
