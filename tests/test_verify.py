"""``python -m pipeline verify STORE`` on a real tiny store (rendered and cleaned through the CLI),
intact and with one kind of damage at a time: each problem is reported naming the file, and the
command exits 1."""
from __future__ import annotations

import json
import shutil

import numpy as np
import OpenEXR
import pytest

from mcdenoise.pipeline.exr import checksum
from mcdenoise.pipeline.verify import verify_store
from tests.helpers import cli

FRAME = "scenes/s00000/000"


@pytest.fixture
def store(cleaned, tmp_path):
    root = tmp_path / "store"
    shutil.copytree(cleaned[0], root)
    return root


@pytest.mark.slow
def test_intact_store_passes(store):
    proc = cli("verify", store)
    assert proc.returncode == 0
    assert proc.stdout.strip().endswith(": 0 problems")
    report = verify_store(store)
    assert report.frames == 6 and report.images == 6 * 6 + 6 and report.incomplete == 0
    assert cli("verify", store, "--headers-only").returncode == 0


def _edit_json(path, fn):
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def _rewrite_exr(path, edit_channels, edit_record=None, compression=None):
    """Rewrite an image with changed pixels, a correct checksum, and a frame.json that agrees,
    so that only the damage under test remains."""
    from mcdenoise.pipeline.store import sha256

    with OpenEXR.File(str(path), separate_channels=True) as f:
        header = dict(f.header())
        chans = {k: v.pixels.copy() for k, v in f.channels().items()}
    record = json.loads(header["mcdenoise"])
    chans = edit_channels(chans)
    if edit_record:
        edit_record(record)
    record["checksum"] = checksum(record, chans)
    with OpenEXR.File({"compression": compression or header["compression"], "type": header["type"],
                       "mcdenoise": json.dumps(record)}, chans) as f:
        f.write(str(path))
    frame = path.parent / "frame.json"
    _edit_json(frame, lambda d: d["images"][path.stem].update({**record, "bytes": path.stat().st_size,
                                                                "sha256": sha256(path)}))


def _flip(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(data))


def _nan(chans):
    # The store is compact: the beauty is the sum of the stored components, a NaN in one reaches it.
    chans["diffuse_direct.R"][3, 4] = np.nan
    return chans


def _extra_mantissa_bit(chans):
    bits = chans["variance.G"].view(np.uint32)
    bits[5, 6] |= 1
    return chans


def _beauty_back(chans):
    chans.update({c: np.zeros_like(chans["diffuse_direct.R"]) for c in "RGB"})     # float32, where the view is half
    return chans


def _view_edited(chans):
    chans["B"][2, 3] = chans["B"][2, 3] * np.float16(2) + np.float16(1)
    return chans


def _drop_albedo_g(chans):
    del chans["albedo.G"]
    return chans


DAMAGE = {
    "bit flip in pixel data": (lambda r: _flip(r / FRAME / "s01.exr"), "s01.exr", "SHA-256 differs"),
    "image deleted": (lambda r: (r / FRAME / "gt2.exr").unlink(), "gt2.exr", "listed in frame.json is missing"),
    "temporary file left": (lambda r: (r / FRAME / ".s02.exr.x1y2.tmp").write_bytes(b"partial"),
                            ".s02.exr.x1y2.tmp", "temporary file"),
    "frame.json spp edited": (lambda r: _edit_json(r / FRAME / "frame.json", lambda d: d["images"]["s00"].update(spp=8)),
                              "s00.exr", "header 'spp' is 4, frame.json records 8"),
    "scene resolution edited": (lambda r: _edit_json(r / "scenes/s00000/scene.json", lambda d: d.update(resolution=[16, 16])),
                                "gt1.exr", "the scene's frames are 16x16"),
    "frame.json removed": (lambda r: (r / FRAME / "frame.json").unlink(), FRAME, "frame is incomplete"),
    "non-finite count edited": (lambda r: _edit_json(r / FRAME / "frame.json", lambda d: d.update(nonfinite=5)),
                                "frame.json", "counts 5 repaired non-finite values, the image headers 0"),
    "NaN in pixels": (lambda r: _rewrite_exr(r / FRAME / "s03.exr", _nan), "s03.exr",
                      "buffer 'color' has 1 non-finite values"),
    "channel dropped": (lambda r: _rewrite_exr(r / FRAME / "gt1.exr", _drop_albedo_g), "gt1.exr",
                        "channel 'albedo.G' of buffer 'albedo' is missing"),
    "constant and stored": (lambda r: _rewrite_exr(r / FRAME / "s00.exr", lambda c: c,
                                                   lambda rec: rec["constants"].update({"diffuse_direct.R": 0.0})),
                            "s00.exr", "channels diffuse_direct.R are stored and also recorded as constants"),
    "variance beyond its mantissa bits": (lambda r: _rewrite_exr(r / FRAME / "s02.exr", _extra_mantissa_bit),
                                          "s02.exr", "buffer 'color.variance' has 1 values with more than the 5"),
    "derived beauty stored": (lambda r: _rewrite_exr(r / FRAME / "s02.exr", _beauty_back), "s02.exr",
                              "the beauty is marked as derived from its components with R, G, B its half view, but "
                              "channel R is float32, G is float32, B is float32, expected float16"),
    "view edited": (lambda r: _rewrite_exr(r / FRAME / "gt2.exr", _view_edited), "gt2.exr",
                    "channels R, G, B (the beauty's half view) differ from the beauty derived from the components in 1"),
    "compact image as PIZ": (lambda r: _rewrite_exr(r / FRAME / "s02.exr", lambda c: c, compression=OpenEXR.PIZ_COMPRESSION),
                             "s02.exr", "compact image compressed with PIZ, expected ZIP or ZSTD"),
    "other cleaner": (lambda r: _edit_json(r / "cleaner.json", lambda d: d.update(sha256="0" * 64)),
                      "gt_clean.exr", "cleaner.json names 000000000000"),
    "gt_clean missing": (lambda r: (r / FRAME / "gt_clean.exr").unlink(), "gt_clean.exr", "listed in cleaner.json but missing"),
    "stray file": (lambda r: (r / FRAME / "notes.txt").write_text("hi"), "notes.txt", "unexpected file"),
    "scene not in manifest": (lambda r: shutil.copytree(r / "scenes/s00000", r / "scenes/s09999"), "s09999",
                              "not listed in dataset.json"),
    "manifest broken": (lambda r: (r / "dataset.json").write_text("{"), "dataset.json", "not valid JSON"),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_damage_is_reported_by_path(store, damage):
    do, where, what = DAMAGE[damage]
    do(store)
    problems = verify_store(store).problems
    hits = [p for p in problems if where in p and what in p]
    assert hits, f"expected a problem about {where} with '{what}', got:\n" + "\n".join(problems[:10])


@pytest.mark.slow
def test_cli_exits_1_and_names_the_file(store):
    (store / FRAME / "gt2.exr").unlink()
    proc = cli("verify", store, check=False)
    assert proc.returncode == 1
    assert f"{store / FRAME / 'gt2.exr'}: image listed in frame.json is missing" in proc.stdout
    assert proc.stdout.strip().splitlines()[-1].endswith(": 1 problem")
    quiet = cli("verify", store, "--headers-only", "--quiet", check=False)
    assert quiet.returncode == 1 and len(quiet.stdout.strip().splitlines()) == 1


def test_missing_store_is_an_error(tmp_path):
    proc = cli("verify", tmp_path / "nothing", check=False)
    assert proc.returncode == 1 and "store folder does not exist" in proc.stdout


@pytest.mark.slow
def test_parallel_verify_reports_the_same(store):
    (store / FRAME / "gt2.exr").unlink()
    _flip(store / "scenes/s00001/001/s02.exr")
    (store / "scenes" / "stray.txt").write_text("x")
    one, two = verify_store(store), verify_store(store, jobs=2)
    # the flipped file fails two checks: its SHA-256 and its decoding
    assert sorted(one.problems) == sorted(two.problems) and len(one.problems) == 4
    assert (one.frames, one.images, one.bytes) == (two.frames, two.images, two.bytes)
    proc = cli("verify", store, "--jobs", "2", check=False)
    assert proc.returncode == 1 and proc.stdout.strip().endswith(": 4 problems")
