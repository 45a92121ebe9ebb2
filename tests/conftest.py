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


def pytest_terminal_summary(terminalreporter):
    """The fuzz and kill counts of this run (tests/test_fuzz.py, tests/test_faults.py), in one place."""
    from tests.helpers import FUZZ_TOTALS, KILL_POINTS

    write = terminalreporter.write_line
    if FUZZ_TOTALS:
        terminalreporter.section("fuzzed inputs")
        totals: dict[str, int] = {}
        for reader, counts in sorted(FUZZ_TOTALS.items()):
            write(f"{reader}: {sum(counts.values())} inputs: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
            for k, v in counts.items():
                totals[k] = totals.get(k, 0) + v
        bad = {k: v for k, v in totals.items() if k not in ("clean error", "correct read", "valid answer")}
        write(f"fuzz total: {sum(totals.values())} inputs across {len(FUZZ_TOTALS)} readers: "
              f"{totals.get('clean error', 0)} clean one-line errors, "
              f"{totals.get('correct read', 0) + totals.get('valid answer', 0)} correct reads, "
              f"{bad.get('crash', 0)} crashes, {bad.get('wrong read', 0)} silent wrong reads")
    if KILL_POINTS:
        terminalreporter.section("kill points")
        for stage, points in KILL_POINTS.items():
            write(f"{stage}: {len(points)} kill points, output identical to an uninterrupted run")
            for p in points:
                write(f"  {p}")
        write(f"kill total: {sum(map(len, KILL_POINTS.values()))} kill points in {len(KILL_POINTS)} stages")
