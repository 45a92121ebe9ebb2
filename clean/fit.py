"""The training loop every trainer runs (cleaner, Isik baseline, AFGSA, diffusion, the stand-in base).

``fit(task)`` trains a ``Task`` to ``task.epochs`` epochs; the task says what differs between
models (its data, one optimisation step, validation, what is saved), the loop does the rest:

- resume: ``<folder>/last.safetensors`` (``pipeline.checkpoint.load_last``, refused when the
  task's fingerprint changed) gives the epoch, the history and the best so far; stale temporary
  files a kill left in the folder are removed first. A run already at ``epochs`` only reports.
- optionally the untrained model's validation as epoch 0 (``validate_initial``), a candidate
  for the best;
- per epoch: the task's batches (on the task's device) through ``task.step``, under a
  ``NanGuard`` (a non-finite step is skipped and counted, ``nan_limit`` in a row stop the run)
  and a progress bar; then, on rank 0: validation, the best checkpoint (``task.save_best`` when
  the score improves; ``task.keep``, e.g. chosen epochs), the history files (``task.write_history``) and ``last.safetensors``,
  written last: it is the commit point of an epoch, so a kill before it reruns the epoch
  (same result) and rewrites the files above;
- ``apply_update``: the optimiser step the tasks share (backward, clipping, the finite check);
- a time budget: the run stops after the epoch during which ``time_budget_s`` passed (a rerun
  resumes);
- a summary dict and line.

Under DDP (``task.world`` > 1) every rank runs the steps; rank 0 validates and writes.
"""
from __future__ import annotations

import contextlib
import time
from pathlib import Path

import numpy as np
import torch

from mcdenoise.pipeline.checkpoint import load_last, save_last
from mcdenoise.pipeline.errors import StoreError, TrainError
from mcdenoise.pipeline.progress import progress


class NanGuard:
    """``ok(finite, epoch, step)``: True for a finite step; a non-finite one is counted (``skipped``)
    and returns False, so the caller skips its update; ``limit`` of them in a row raise ``error``."""

    def __init__(self, name: str, limit: int, error: type[Exception] = StoreError):
        self.name, self.limit, self.error = name, int(limit), error
        self.skipped = self.in_row = 0

    def ok(self, finite: bool, epoch: int, step: int) -> bool:
        if finite:
            self.in_row = 0
            return True
        self.skipped += 1
        self.in_row += 1
        if self.in_row >= self.limit:
            raise self.error(f"{self.name}: {self.in_row} steps in a row had a non-finite loss or gradient "
                             f"(epoch {epoch + 1}, step {step}); check the data (python -m pipeline inspect) "
                             "or lower the learning rate")
        return False


class Task:
    """What ``fit`` needs from one model; subclasses set the attributes and override the hooks.

    Attributes: ``name`` (log lines, progress bar), ``folder`` (the run folder), ``epochs``,
    ``time_budget_s`` (0: none), ``nan_limit``, ``fingerprint`` (settings a resume must share),
    ``fmt`` (the checkpoint's format tag), ``state`` (the module saved in last.safetensors),
    ``optimizers`` (an optimizer or a dict of them), ``device``, ``minimize`` (lower scores are
    better), ``validate_initial``, ``rank`` and ``world`` (DDP)."""

    name: str
    folder: Path
    epochs: int
    time_budget_s: float = 0.0
    nan_limit: int = 3
    fingerprint: dict
    fmt: str
    state: torch.nn.Module
    optimizers: object
    device: torch.device
    minimize: bool = True
    validate_initial: bool = False
    rank: int = 0
    world: int = 1

    # ---- resume and the end of a run
    def resume(self, record: dict, extra: dict) -> None:
        """Restore what ``checkpoint`` added to last.safetensors (the weights and optimizers are back already)."""

    def when_done(self, history: list, best: dict | None) -> None:
        """Called instead of training when the run is already at ``epochs``."""

    def prepare(self) -> None:
        """Before the first epoch of this invocation (data sets, DDP wrapping, ...)."""

    def finish(self) -> None:
        """After the last epoch of this invocation, on every rank."""

    # ---- an epoch
    def guard(self) -> NanGuard:
        """The NaN guard of the next epoch (one per epoch here; a task may keep one for the run)."""
        return NanGuard(self.name, self.nan_limit, TrainError)

    def batches(self, epoch: int):
        """The epoch's batches (dicts of tensors); the state is in training mode."""
        raise NotImplementedError

    def step(self, batch: dict, epoch: int, index: int) -> tuple[dict, bool]:
        """One optimisation step: ({"loss": float, other terms}, whether it was finite and applied)."""
        raise NotImplementedError

    def entry(self, epoch: int, kept: list[dict], skipped: int) -> dict:
        """The history entry of an epoch from the terms of its finite steps (``val``, ``seconds`` are added)."""
        raise NotImplementedError

    def initial_entry(self) -> dict:
        """The history entry of epoch 0 (``validate_initial``)."""
        return {"epoch": 0, "train_loss": None}

    # ---- validation and files
    def validate(self) -> dict | None:
        return None

    def evaluation(self):
        """Context of validation and saving the best (e.g. with the EMA of the weights in place)."""
        return contextlib.nullcontext()

    def score(self, entry: dict) -> float | None:
        """What picks the best epoch (None: not a candidate)."""
        raise NotImplementedError

    def save_best(self, entry: dict) -> None:
        raise NotImplementedError

    def keep(self, entry: dict) -> None:
        """After every epoch's validation, with the evaluated weights in place: a task may keep that epoch's
        weights beside the best (the best is chosen on the run's validation split alone)."""

    def write_history(self, history: list, best: dict | None) -> None:
        raise NotImplementedError

    def checkpoint(self) -> tuple[dict, dict | None]:
        """(record fields, extra tensors) added to last.safetensors."""
        return {}, None

    # ---- report
    def epoch_line(self, entry: dict) -> str:
        raise NotImplementedError

    def best_text(self, best: dict) -> str:
        """The summary line's description of the best epoch (after ``; ``)."""
        return f"best epoch {best['epoch']}: train loss {best['train_loss']:.4f}"

    def summary_fields(self) -> dict:
        return {}

    output: str = ""   # what the summary line points to (default: the folder)


def apply_update(loss: torch.Tensor, opt: torch.optim.Optimizer, params: list, grad_clip: float) -> bool:
    """Backward, clip, step; a non-finite loss or gradient norm skips the step (returns False)."""
    opt.zero_grad(set_to_none=True)
    loss.backward()
    # max_norm inf measures without clipping (the gradients are multiplied by exactly 1).
    norm = torch.nn.utils.clip_grad_norm_(params, grad_clip if grad_clip > 0 else float("inf"))
    if not (torch.isfinite(loss) and torch.isfinite(norm)):
        opt.zero_grad(set_to_none=True)
        return False
    opt.step()
    return True


def fit(task: Task, quiet: bool = False) -> dict:
    """Train (or resume) ``task`` to ``task.epochs``; return a summary."""
    quiet = quiet or task.rank != 0
    folder = task.folder
    last = folder / "last.safetensors"
    history: list[dict] = []
    best: dict | None = None
    start = 0
    if task.rank == 0 and folder.is_dir():
        # Temporary files of a write a kill interrupted (one trainer per run folder: all stale).
        for tmp in folder.glob(".*.tmp"):
            tmp.unlink(missing_ok=True)
    if last.exists():
        extra: dict = {}
        record = load_last(last, task.state, task.optimizers, task.device, extra=extra, fingerprint=task.fingerprint)
        start, history, best = int(record["epoch"]), record["history"], record["best"]
        task.resume(record, extra)
    if start >= task.epochs:
        task.when_done(history, best)
        summary = _summary(task, history, best, 0, 0.0)
        if not quiet:
            print(f"{task.name}: already trained ({start} epochs); {summary['line']}")
        return summary

    task.prepare()
    # The run's clock (time budget, ``seconds``) starts with the data loaded, as the diffusion trainer's
    t_start = time.perf_counter()
    if start == 0 and task.validate_initial and task.rank == 0:
        best = _initial(task, history)
    trained = 0
    for epoch in range(start, task.epochs):
        entry = _train_epoch(task, epoch, quiet)
        if task.rank == 0:
            best = _end_epoch(task, entry, history, best, t_start)
            if not quiet:
                print(task.epoch_line(entry), flush=True)
        trained += 1
        if task.world > 1:
            torch.distributed.barrier()
        if task.time_budget_s > 0 and time.perf_counter() - t_start >= task.time_budget_s and epoch + 1 < task.epochs:
            if not quiet:
                print(f"{task.name}: time budget of {task.time_budget_s:g} s reached after epoch {epoch + 1}; "
                      "rerun to resume")
            break
    task.finish()
    if task.world > 1:
        # Leave together: a rank that tears gloo down while its peer still writes files can abort the peer
        # at exit ("terminate called without an active exception"). Only on success: after an error a
        # barrier could wait for a rank that is gone.
        torch.distributed.barrier()
    summary = _summary(task, history, best, trained, time.perf_counter() - t_start)
    if not quiet:
        print(summary["line"], flush=True)
    return summary


def _train_epoch(task: Task, epoch: int, quiet: bool) -> dict:
    """One pass over the epoch's batches; the history entry without ``val`` and ``seconds``."""
    guard, kept = task.guard(), []
    bar = progress(task.batches(epoch), desc=f"{task.name} epoch {epoch + 1}/{task.epochs}", unit="step",
                   disable=quiet, leave=False)
    for i, batch in enumerate(bar):
        terms, finite = task.step({k: v.to(task.device) for k, v in batch.items()}, epoch, i)
        if guard.ok(finite, epoch, i):
            kept.append(terms)
            bar.set_postfix(loss=f"{np.mean([t['loss'] for t in kept]):.4f}")
    return task.entry(epoch, kept, guard.skipped)


def _better(task: Task, score: float | None, best: dict | None) -> bool:
    if score is None:
        return False
    return best is None or (score < best["score"] if task.minimize else score > best["score"])


def _end_epoch(task: Task, entry: dict, history: list, best: dict | None, t_start: float) -> dict | None:
    """Validate, keep the best, write the history and the epoch's checkpoint (rank 0); the new best."""
    with task.evaluation():
        entry["val"] = task.validate()
        entry["seconds"] = round(time.perf_counter() - t_start, 2)
        history.append(entry)
        score = task.score(entry)
        if _better(task, score, best):
            best = {"epoch": entry["epoch"], "score": score, "val": entry["val"], "train_loss": entry["train_loss"]}
            task.save_best(entry)
        task.keep(entry)
    task.write_history(history, best)
    fields, tensors = task.checkpoint()
    save_last(task.folder / "last.safetensors", task.state, task.optimizers,
              {"epoch": entry["epoch"], "history": history, "best": best, "fingerprint": task.fingerprint, **fields},
              task.fmt, extra=tensors)
    return best


def _initial(task: Task, history: list) -> dict | None:
    """Epoch 0: the untrained model's validation score, saved as the best so far (none without validation)."""
    val = task.validate()
    if val is None:
        return None
    entry = {**task.initial_entry(), "val": val, "seconds": 0.0}
    history.append(entry)
    task.save_best(entry)
    return {"epoch": 0, "score": task.score(entry), "val": val, "train_loss": None}


def _summary(task: Task, history: list, best: dict | None, trained: int, seconds: float) -> dict:
    epochs = history[-1]["epoch"] if history else 0
    line = f"{task.name}: {epochs} epochs ({trained} this run, {seconds:.1f} s)"
    if best:
        line += "; " + task.best_text(best)
    line += f" -> {task.output or task.folder}"
    return {**task.summary_fields(), "folder": str(task.folder), "epochs": epochs, "trained_epochs": trained,
            "best": best, "seconds": seconds, "line": line}
