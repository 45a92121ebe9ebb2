"""``denoise`` on every kind of bad input a user hands it: exactly one line on stderr naming the file and what was
expected, nothing on stdout, exit status 2, and no output file."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from tests.helpers import write_rgb_exr

ROOT = Path(__file__).resolve().parents[1]


def denoise(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline", "denoise", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)


def cases(tmp: Path) -> dict[str, tuple[list, str]]:
    """name -> (denoise's arguments, what the one line must say)."""
    good = tmp / "good.exr"
    write_rgb_exr(good, np.random.default_rng(0).gamma(2.0, 0.2, (24, 32, 3)).astype(np.float32))
    truncated = tmp / "truncated.exr"
    truncated.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    text = tmp / "text.exr"
    text.write_text("not an image\n")
    no_rgb = tmp / "no_rgb.exr"
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, {"Y": np.ones((8, 8), np.float32)}) as f:
        f.write(str(no_rgb))
    folder = tmp / "folder"
    folder.mkdir()
    return {
        "missing": (["--exr", tmp / "missing.exr", "--out", tmp / "o1.exr"], "missing.exr: no such file"),
        "folder": (["--exr", folder, "--out", tmp / "o2.exr"], "folder: a folder, expected an EXR file"),
        "truncated": (["--exr", truncated, "--out", tmp / "o3.exr"], "truncated.exr: corrupt or truncated EXR"),
        "not an EXR": (["--exr", text, "--out", tmp / "o4.exr"], "text.exr: not an OpenEXR file"),
        "no R,G,B": (["--exr", no_rgb, "--out", tmp / "o5.exr"], "no_rgb.exr: channels R, G, B"),
        "out is the input": (["--exr", good, "--out", good], "that is the input"),
        "out is the input (oidn)": (["--exr", good, "--out", good, "--method", "oidn"], "that is the input"),
        "out is a folder": (["--exr", good, "--out", folder], "a folder, expected the name of the EXR file"),
    }


@pytest.mark.slow
def test_every_bad_input_is_one_line_exit_2_and_no_output(tmp_path):
    table = cases(tmp_path)
    good_bytes = (tmp_path / "good.exr").read_bytes()
    before = sorted(p.name for p in tmp_path.iterdir())
    for name, (args, says) in table.items():
        proc = denoise(*args)
        lines = proc.stderr.splitlines()
        assert proc.returncode == 2, (name, proc.stderr)
        assert len(lines) == 1 and lines[0].startswith("error: ") and says in lines[0], (name, proc.stderr)
        assert proc.stdout == "", (name, proc.stdout)
    assert sorted(p.name for p in tmp_path.iterdir()) == before          # nothing written, nothing left behind
    assert (tmp_path / "good.exr").read_bytes() == good_bytes            # the input was not overwritten
