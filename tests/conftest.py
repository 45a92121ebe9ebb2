"""Fixtures shared by several test modules. The rendered ones are session-scoped: the tiny
dataset renders (and is cleaned) once per test run, not once per module that uses it. Tests must
not change these stores; a test that damages or extends one works on a copy."""
import json
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


def pytest_sessionfinish(session):
    """In a pytest-xdist worker (make test runs several): hand this worker's fuzz and kill counts to the
    controller, which prints the summary."""
    out = getattr(session.config, "workeroutput", None)
    if out is not None:
        from tests.helpers import FUZZ_TOTALS, KILL_POINTS
        out["fuzz_totals"], out["kill_points"] = json.dumps(FUZZ_TOTALS), json.dumps(KILL_POINTS)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """The controller: a worker's counts, added to its own (empty under xdist)."""
    from tests.helpers import FUZZ_TOTALS, KILL_POINTS

    out = getattr(node, "workeroutput", {})
    for reader, counts in json.loads(out.get("fuzz_totals", "{}")).items():
        mine = FUZZ_TOTALS.setdefault(reader, {})
        for k, v in counts.items():
            mine[k] = mine.get(k, 0) + v
    for stage, points in json.loads(out.get("kill_points", "{}")).items():
        KILL_POINTS.setdefault(stage, []).extend(points)


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
