"""The wheel: one top-level name (``mcdenoise``) holding the card's folders and the shipped model,
and a command line that runs from any directory. Built from a copy of the tracked files, so the
checkout gets no build/ or egg-info."""
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("pipeline", "render", "clean", "train", "evaluate")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("wheel")
    tracked = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, check=True,
                             capture_output=True, text=True).stdout.split("\n")
    src = tmp / "src"
    for rel in filter(None, tracked):
        if (ROOT / rel).is_file():
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / rel, src / rel)
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                           "--disable-pip-version-check", "-w", str(tmp / "dist"), str(src)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    (built,) = (tmp / "dist").glob("mcdenoise-*.whl")
    return built


@pytest.mark.slow
def test_the_wheel_installs_one_name_with_every_module_and_the_shipped_model(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names} == {"mcdenoise", wheel.name.split("-py3")[0] + ".dist-info"}
    expected = {f"mcdenoise/{p.relative_to(ROOT).as_posix()}" for f in FOLDERS for p in (ROOT / f).glob("*.py")}
    assert expected <= set(names), sorted(expected - set(names))
    shipped = {f"mcdenoise/{p.relative_to(ROOT).as_posix()}" for d in ("train/shipped",)
               for p in (ROOT / d).rglob("*") if p.is_file()}
    assert shipped <= set(names), sorted(shipped - set(names))
    entry = zipfile.ZipFile(wheel).read(wheel.name.split("-py3")[0] + ".dist-info/entry_points.txt").decode()
    assert "mcdenoise = mcdenoise.__main__:run" in entry


@pytest.mark.slow
def test_the_unpacked_wheel_runs_from_another_directory(wheel, tmp_path):
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    env = os.environ | {"PYTHONPATH": str(site)}
    run = lambda *a: subprocess.run([sys.executable, *a], cwd=tmp_path, capture_output=True, text=True, env=env,
                                    timeout=300)
    proc = run("-m", "mcdenoise", "--help")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: python -m mcdenoise") and "denoise" in proc.stdout
    probe = ("import mcdenoise, mcdenoise.train.model as m, mcdenoise.evaluate.stability as s; "
             "print(mcdenoise.__path__, m.SHIPPED_MODEL.is_dir(), s.__file__)")
    proc = run("-c", probe)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == [f"['{site / 'mcdenoise'}']", "True", str(site / "mcdenoise/evaluate/stability.py")]
