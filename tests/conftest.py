"""Fixtures shared by several test modules. The rendered ones are session-scoped: the tiny
dataset renders (and is cleaned) once per test run, not once per module that uses it. Tests must
not change these stores; a test that damages or extends one works on a copy."""
import shutil

import pytest

from tests.helpers import CLEAN_TINY, TINY, cli


@pytest.fixture(scope="session")
def tiny_store(tmp_path_factory):
    """configs/tiny.yaml rendered through the command line: (store root, the finished process)."""
    root = tmp_path_factory.mktemp("tiny") / "store"
    proc = cli("dataset", "--config", TINY, f"store={root}")
    return root, proc


@pytest.fixture(scope="session")
def cleaned(tiny_store, tmp_path_factory):
    """The tiny store after an uninterrupted gt-clean: the reference, and the baselines' input."""
    reference, _ = tiny_store
    base = tmp_path_factory.mktemp("cleaned")
    store, runs = base / "store", base / "runs"
    shutil.copytree(reference, store)
    cli("gt-clean", "--config", TINY, f"store={store}", f"runs={runs}", *CLEAN_TINY, "--quiet")
    return store, runs
