"""The errors a user can act on, under one base class.

``python -m pipeline`` catches ``PipelineError`` in one place: it prints ``error: <message>`` as
one line on stderr and exits with status 2. Each class also derives from the built-in exception
that fits it (``ValueError``, ``RuntimeError``, ``OSError``, ``ImportError``), so code that catches
those catches it too.

- ``ConfigError``: a config file or override is malformed (``pipeline.config``).
- ``StoreError``: something in the store is missing, corrupt or not what the schema expects
  (``pipeline.exr``); ``StoreWriteError``: writing into the store failed.
- ``CheckpointError``: a checkpoint or trained-run folder cannot be used (another trainer's, other
  settings, another model, not safetensors). A ``StoreError``: a run folder is files on disk, and
  callers that handle an unusable store handle it too.
- ``TrainError``: a training run cannot proceed (no data, bad arguments, diverged ranks); a
  ``StoreError`` too.
- ``MitsubaSetupError``: Mitsuba or its LLVM backend cannot be used here (``pipeline.mitsuba_env``).
- ``OIDNUnavailable``: ``pyoidn`` cannot be imported here (``train.oidn``).
- ``WeightsError``: OIDN's weights cannot be found or read (a ``.tza`` file, the blobs inside
  pyoidn's library: ``pipeline.weights``, ``train.oidn``).
- ``TaskFailed``: a task of the executor failed for good (``pipeline.executors``).

Stage-specific errors derive from ``PipelineError`` where they are defined
(``render.frame.ExternalSceneError``, ``train.sampler.FormulationError`` via
``ConfigError``, ``evaluate.methods.MethodUnavailable``).
"""
from __future__ import annotations


class PipelineError(Exception):
    """An error the user can act on; the command line prints it as one line and exits with status 2."""


class ConfigError(PipelineError, ValueError):
    """A config file or override is malformed; the message names the source and the key."""


class StoreError(PipelineError, RuntimeError):
    """Something in the store is missing, corrupt or not what the schema expects."""


class StoreWriteError(StoreError, OSError):
    """Writing into the store failed (full disk, read-only folder, ...); nothing was left behind.

    Also an ``OSError``, so code that handles I/O errors generically still catches it."""


class CheckpointError(StoreError):
    """A checkpoint or a trained run's folder cannot be used; the message names the file and what to do."""


class TrainError(StoreError):
    """The run cannot proceed (no data, incompatible checkpoint, bad arguments); the message says what to do."""


class MitsubaSetupError(PipelineError, RuntimeError):
    """Mitsuba or the LLVM library its CPU variants need cannot be used here."""


class OIDNUnavailable(PipelineError, ImportError):
    """pyoidn cannot be imported here."""


class WeightsError(PipelineError, ValueError):
    """OIDN weights cannot be found or read; the message names the file looked in and the fix."""


class TaskFailed(PipelineError, RuntimeError):
    """A task of the executor failed for good (after its retries), or the executor cannot start."""


def innermost_message(exc: BaseException) -> str:
    """The first line of the deepest exception in ``exc``'s chain (``__cause__``, else ``__context__``).

    drjit reports a failure inside a render as "error while performing a custom differentiable
    operation (see above)"; what went wrong (a plugin's own message) is two or three causes down."""
    seen = {id(exc)}
    while (nxt := exc.__cause__ or exc.__context__) is not None and id(nxt) not in seen:
        seen.add(id(nxt))
        exc = nxt
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
