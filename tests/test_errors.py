"""One error base class: every error a user can act on is a ``PipelineError``, derives from the
built-in exception that fits it, and the command line turns any of them into one line on stderr and exit status 2."""
import pytest

import mcdenoise.pipeline.cli as cli_main
from mcdenoise.evaluate.methods import MethodUnavailable
from mcdenoise.pipeline.errors import (
    CheckpointError,
    ConfigError,
    MitsubaSetupError,
    OIDNUnavailable,
    PipelineError,
    StoreError,
    StoreWriteError,
    TaskFailed,
    TrainError,
)
from mcdenoise.render.frame import ExternalSceneError
from mcdenoise.train.sampler import FormulationError

BUILTIN_BASES = {ConfigError: ValueError, StoreError: RuntimeError, StoreWriteError: OSError,
                 CheckpointError: RuntimeError, TrainError: RuntimeError, MitsubaSetupError: RuntimeError,
                 OIDNUnavailable: ImportError, TaskFailed: RuntimeError, ExternalSceneError: RuntimeError,
                 FormulationError: ValueError, MethodUnavailable: Exception}


@pytest.mark.parametrize("cls", list(BUILTIN_BASES), ids=lambda c: c.__name__)
def test_every_error_is_a_pipeline_error_and_keeps_its_builtin_base(cls):
    assert issubclass(cls, PipelineError) and issubclass(cls, BUILTIN_BASES[cls])


def test_checkpoint_and_train_errors_are_store_errors():
    # A run folder is files on disk: callers that handle an unusable store (StoreError) handle these too.
    assert issubclass(CheckpointError, StoreError) and issubclass(TrainError, StoreError)


def test_train_error_is_one_class():
    from mcdenoise.clean.train import TrainError as clean_train_error
    from mcdenoise.train.train import TrainError as diffusion_train_error
    assert clean_train_error is diffusion_train_error is TrainError


@pytest.mark.parametrize("cls", list(BUILTIN_BASES), ids=lambda c: c.__name__)
def test_the_command_line_prints_one_line_and_exits_2(cls, monkeypatch, capsys):
    def fail():
        raise cls("the culprit: what to do")
    monkeypatch.setattr(cli_main, "documentation_markdown", fail)
    assert cli_main.main(["config", "--doc"]) == 2
    err = capsys.readouterr().err
    assert err == "error: the culprit: what to do\n"


def test_other_exceptions_are_not_swallowed(monkeypatch):
    def fail():
        raise ZeroDivisionError("a bug")
    monkeypatch.setattr(cli_main, "documentation_markdown", fail)
    with pytest.raises(ZeroDivisionError):
        cli_main.main(["config", "--doc"])
