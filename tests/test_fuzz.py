"""Fuzzing the store's readers with damaged files (hypothesis, derandomized for CI).

Every damaged EXR (truncated, bit-flipped, header bytes overwritten, header fields patched to
absurd values, channels renamed or retyped, the ``mcdenoise`` record mutated) must give either a
``StoreError`` or a read that returns exactly the original data; anything else (another
exception, a native crash, a hang, different data) fails the test. The reads run in a separate
reader process with a time limit per case, so a native crash in OpenEXR or a hang is observed as
such instead of killing pytest. Malformed manifests (dataset.json, scene.json, frame.json) go
through the Store API in process (pure Python): StoreError or a valid answer.

Each test prints how many cases ran and how they ended.
"""
from __future__ import annotations

import hashlib
import json
import os
import select
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.exr import ENCODINGS, VOLATILE_KEYS, StoreError, read_image, write_image
from mcdenoise.pipeline.store import Store
from tests.helpers import all_keys

ROOT = Path(__file__).resolve().parents[1]
CASE_TIMEOUT_S = 30
FUZZ = settings(derandomize=True, deadline=None, database=None,
                suppress_health_check=list(HealthCheck), max_examples=700)


# ---- the reader process -----------------------------------------------------------------------

def digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for k in sorted(arrays):
        h.update(k.encode())
        h.update(np.ascontiguousarray(arrays[k]).tobytes())
    return h.hexdigest()


def stable(record: dict) -> dict:
    return {k: v for k, v in record.items() if k not in VOLATILE_KEYS}


def reader_main() -> None:
    """Read one path per stdin line; answer one JSON line per path."""
    # OpenEXR's C++ core prints diagnostics on stdout: keep the answer channel to ourselves.
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    for line in sys.stdin:
        path = line.strip()
        try:
            arrays, record = read_image(path)
            out = {"ok": True, "digest": digest(arrays), "record": stable(record)}
        except StoreError as exc:
            out = {"ok": False, "error": "StoreError", "message": str(exc)}
        except BaseException as exc:  # noqa: BLE001 - reported to the test, which fails on it
            out = {"ok": False, "error": type(exc).__name__, "message": str(exc)[:500]}
        print(json.dumps(out), file=answers, flush=True)


class Reader:
    """A long-lived reader subprocess; restarted after a crash or a hang."""

    def __init__(self):
        self.proc = None

    def start(self):
        env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        self.proc = subprocess.Popen([sys.executable, "-c", "from tests.test_fuzz import reader_main; reader_main()"],
                                     cwd=ROOT, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def read(self, path: Path) -> dict:
        if self.proc is None or self.proc.poll() is not None:
            self.start()
        self.proc.stdin.write(f"{path}\n")
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.proc.stdout], [], [], CASE_TIMEOUT_S)
        if not ready:
            self.close()
            return {"ok": False, "error": "hang", "message": f"no answer within {CASE_TIMEOUT_S} s"}
        line = self.proc.stdout.readline()
        if not line:
            code = self.proc.wait()
            self.proc = None
            return {"ok": False, "error": "crash", "message": f"reader process died with status {code}"}
        return json.loads(line)

    def close(self):
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None


@pytest.fixture(scope="module")
def reader():
    r = Reader()
    yield r
    r.close()


@pytest.fixture(scope="module", params=ENCODINGS)
def original(request, tmp_path_factory):
    """A valid image in each encoding (``_original``): every fuzz test runs on both."""
    return _original(tmp_path_factory, request.param)


@pytest.fixture(scope="module")
def exact_original(tmp_path_factory):
    return _original(tmp_path_factory, "exact")


def _original(tmp_path_factory, encoding: str) -> dict:
    """A valid 20x12 image with every buffer, some constant channels and a volatile field; in the
    compact encoding the beauty is the sum of its components, so the reader derives it."""
    rng = np.random.default_rng(5)
    arrays = {}
    for b in schema.BUFFERS:
        arrays[b.name] = rng.random((12, 20, b.size)).astype(np.float32) * 4
        arrays[schema.variance_name(b.name)] = (rng.random((12, 20, b.size)) * 1e-3).astype(np.float32)
    arrays["transmission"][:] = 0.0
    if encoding == "compact":
        arrays["color"] = schema.beauty_from_components(arrays)
    path = tmp_path_factory.mktemp("fuzz") / "orig.exr"
    write_image(path, arrays, meta={"image": "gt1", "spp": 64, "seed": 3, "render_seconds": 1.25}, encoding=encoding)
    read, record = read_image(path)
    return {"bytes": path.read_bytes(), "digest": digest(read), "record": stable(record), "path": path}


class Tally:
    def __init__(self, name: str):
        self.name, self.counts, self.failures = name, Counter(), []

    def check(self, result: dict, original: dict, case: str) -> None:
        if result["ok"]:
            if result["digest"] == original["digest"] and result["record"] == original["record"]:
                self.counts["correct read"] += 1
            else:
                self.counts["WRONG DATA"] += 1
                self.failures.append(f"{case}: read succeeded with different data or record")
        elif result["error"] == "StoreError":
            self.counts["StoreError"] += 1
        else:
            self.counts[result["error"]] += 1
            self.failures.append(f"{case}: {result['error']}: {result['message']}")

    def report(self, capsys) -> None:
        with capsys.disabled():
            total = sum(self.counts.values())
            print(f"\nfuzz {self.name}: {total} cases: " + ", ".join(f"{k} {v}" for k, v in sorted(self.counts.items())))
        assert not self.failures, "\n".join(self.failures[:10])
        assert self.counts["StoreError"] > 0


def _case(tmp_path: Path, data: bytes) -> Path:
    path = tmp_path / "case.exr"
    path.write_bytes(data)
    return path


# ---- EXR mutations -----------------------------------------------------------------------------

def test_fuzz_truncated(reader, original, tmp_path_factory, capsys):
    tally, tmp = Tally("truncated EXR"), tmp_path_factory.mktemp("trunc")
    data = original["bytes"]

    @FUZZ
    @given(st.integers(0, len(data) - 1))
    def case(n):
        tally.check(reader.read(_case(tmp, data[:n])), original, f"truncated to {n} bytes")

    case()
    tally.report(capsys)
    assert tally.counts["correct read"] == 0


def test_fuzz_bit_flips(reader, original, tmp_path_factory, capsys):
    tally, tmp = Tally("bit-flipped EXR"), tmp_path_factory.mktemp("flip")
    data = original["bytes"]

    @FUZZ
    @given(st.lists(st.integers(0, len(data) * 8 - 1), min_size=1, max_size=4, unique=True),
           st.booleans())
    def case(bits, in_header):
        buf = bytearray(data)
        for b in bits:
            # Half the cases aim at the header (the first ~3 KiB), where damage is subtle.
            pos = (b // 8) % 3000 if in_header else b // 8
            buf[pos] ^= 1 << (b % 8)
        tally.check(reader.read(_case(tmp, bytes(buf))), original, f"bits {bits} header={in_header}")

    case()
    tally.report(capsys)


def test_fuzz_overwritten_bytes(reader, original, tmp_path_factory, capsys):
    tally, tmp = Tally("overwritten EXR bytes"), tmp_path_factory.mktemp("over")
    data = original["bytes"]

    @FUZZ
    @given(st.integers(0, len(data) - 1), st.binary(min_size=1, max_size=16))
    def case(pos, junk):
        buf = bytearray(data)
        buf[pos:pos + len(junk)] = junk
        tally.check(reader.read(_case(tmp, bytes(buf[:len(data)]))), original, f"{junk!r} at {pos}")

    case()
    tally.report(capsys)


def _attr_value_offset(data: bytes, name: str) -> int:
    """Byte offset of the value of header attribute ``name`` (after name, type and size)."""
    i = data.index(name.encode() + b"\0")
    j = data.index(b"\0", i + len(name) + 1)
    return j + 1 + 4


def test_fuzz_absurd_dimensions(reader, original, tmp_path_factory, capsys):
    """Header claims up to 2^31 pixels a side (1e9 x 1e9 included): refused before any allocation."""
    tally, tmp = Tally("absurd data/display windows"), tmp_path_factory.mktemp("dims")
    data = original["bytes"]
    off = _attr_value_offset(data, "dataWindow")
    box = st.integers(-(2 ** 31), 2 ** 31 - 1)

    @FUZZ
    @given(st.one_of(st.tuples(box, box, box, box),
                     st.just((0, 0, 10 ** 9 - 1, 10 ** 9 - 1)), st.just((0, 0, 19, 10 ** 9))))
    def case(window):
        buf = bytearray(data)
        buf[off:off + 16] = b"".join(int(v).to_bytes(4, "little", signed=True) for v in window)
        tally.check(reader.read(_case(tmp, bytes(buf))), original, f"dataWindow {window}")

    case()
    tally.report(capsys)
    assert tally.counts["correct read"] == 0


def _rewrite(src: Path, dst: Path, header_fn=None, channels_fn=None) -> None:
    """Re-encode an image through OpenEXR with a changed header and/or channels."""
    with OpenEXR.File(str(src), separate_channels=True) as f:
        header = dict(f.header())
        chans = {k: v.pixels.copy() for k, v in f.channels().items()}
    header = {k: header[k] for k in ("compression", "type", "mcdenoise")}
    if header_fn:
        header = header_fn(header)
    if channels_fn:
        chans = channels_fn(chans)
    with OpenEXR.File(header, chans) as f:
        f.write(str(dst))


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-10 ** 12, 10 ** 12) | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=8)


def test_fuzz_record_mutations(reader, original, tmp_path_factory, capsys):
    """The ``mcdenoise`` record with keys removed, values replaced, or not JSON at all."""
    tally, tmp = Tally("mutated mcdenoise records"), tmp_path_factory.mktemp("rec")
    record = json.loads(OpenEXR.File(str(original["path"]), header_only=True).header()["mcdenoise"])
    keys = sorted(record)

    @FUZZ
    @given(st.one_of(
        st.tuples(st.just("drop"), st.sampled_from(keys), st.none()),
        st.tuples(st.just("set"), st.sampled_from(keys + ["extra"]), json_values),
        st.tuples(st.just("constant"), st.sampled_from(sorted(record["constants"])), json_values),
        st.tuples(st.just("text"), st.just(""), st.text(max_size=40)),
    ))
    def case(mutation):
        kind, key, value = mutation
        rec = json.loads(json.dumps(record))
        if kind == "drop":
            del rec[key]
        elif kind == "set":
            rec[key] = value
        elif kind == "constant":
            rec["constants"][key] = value
        text = value if kind == "text" else json.dumps(rec)
        path = tmp / "case.exr"
        _rewrite(original["path"], path, header_fn=lambda h: {**h, "mcdenoise": text})
        tally.check(reader.read(path), original, f"{mutation!r}")

    case()
    tally.report(capsys)


def test_fuzz_channel_names_and_types(reader, original, tmp_path_factory, capsys):
    """Channels renamed (to other schema names or foreign ones), dropped, added or retyped."""
    tally, tmp = Tally("renamed/retyped channels"), tmp_path_factory.mktemp("chan")
    with OpenEXR.File(str(original["path"]), separate_channels=True) as f:
        names = sorted(f.channels())
    foreign = st.sampled_from(["A", "Z", "N.W", "color.R", "albedo.variance.A", "R ", "r"])
    dtypes = st.sampled_from([np.float16, np.float32, np.uint32])

    @FUZZ
    @given(st.sampled_from(names), st.one_of(st.tuples(st.just("rename"), foreign | st.sampled_from(names)),
                                             st.tuples(st.just("retype"), dtypes),
                                             st.tuples(st.just("drop"), st.none()),
                                             st.tuples(st.just("add"), foreign)))
    def case(name, change):
        kind, arg = change

        def edit(chans):
            chans = dict(chans)
            if kind == "rename":
                chans[arg] = chans.pop(name)
            elif kind == "retype":
                chans[name] = chans[name].astype(arg)
            elif kind == "drop":
                del chans[name]
            else:
                chans[arg] = np.zeros_like(chans[name])
            return chans

        path = tmp / "case.exr"
        _rewrite(original["path"], path, channels_fn=edit)
        tally.check(reader.read(path), original, f"{name}: {change!r}")

    case()
    tally.report(capsys)


# ---- manifests ---------------------------------------------------------------------------------

def _good_store(root: Path) -> Store:
    store = Store(root)
    store.write_manifest({"scenes": ["s0"], "splits": {"train": ["s0"]}, "images": ["s00"]})
    store.write_scene_manifest("s0", {"frames": 1, "resolution": [20, 12], "gt_spp": 64, "stack_spp": 4,
                                      "stacks": 1, "images": ["s00"]})
    rng = np.random.default_rng(0)
    arrays = {k: rng.random((12, 20, schema.BY_NAME[k.removesuffix(".variance")].size)).astype(np.float32)
              for k in all_keys()}
    rec = store.write_image("s0", 0, "s00", arrays)
    store.write_frame_record("s0", 0, {"images": {"s00": rec}})
    return store


def _exercise(store: Store) -> None:
    """What the stages ask of a store."""
    for key in store.frames():
        store.is_frame_complete(key.scene, key.frame, ["s00"])
        rec = store.frame_record(key.scene, key.frame)
        if rec is not None:
            store.read(key.scene, key.frame, 4)


def test_fuzz_manifests(tmp_path_factory, capsys):
    tally = Counter()
    failures = []
    root = tmp_path_factory.mktemp("manifests") / "store"
    _good_store(root)
    files = {"dataset.json": root / "dataset.json", "scene.json": root / "scenes/s0/scene.json",
             "frame.json": root / "scenes/s0/000/frame.json"}
    originals = {k: p.read_bytes() for k, p in files.items()}

    @FUZZ
    @given(st.sampled_from(sorted(files)),
           st.one_of(st.tuples(st.just("value"), st.text(max_size=12), json_values),
                     st.tuples(st.just("bytes"), st.integers(0, 10 ** 6), st.binary(max_size=8)),
                     st.tuples(st.just("whole"), st.just(""), json_values)))
    def case(which, mutation):
        kind, key, value = mutation
        for k, p in files.items():
            p.write_bytes(originals[k])
        path = files[which]
        if kind == "value":
            data = json.loads(originals[which])
            keys = sorted(data)
            data[keys[hash(key) % len(keys)] if key else "extra"] = value
            path.write_text(json.dumps(data))
        elif kind == "bytes":
            buf = bytearray(originals[which])
            pos = key % len(buf)
            buf[pos:pos + len(value)] = value
            path.write_bytes(bytes(buf))
        else:
            path.write_text(json.dumps(value))
        try:
            _exercise(Store(root))
            tally["valid answer"] += 1
        except StoreError:
            tally["StoreError"] += 1
        except Exception as exc:  # noqa: BLE001
            tally[type(exc).__name__] += 1
            failures.append(f"{which} {mutation!r}: {type(exc).__name__}: {exc}")

    case()
    with capsys.disabled():
        print(f"\nfuzz manifests: {sum(tally.values())} cases: " + ", ".join(f"{k} {v}" for k, v in sorted(tally.items())))
    assert not failures, "\n".join(failures[:10])
    assert tally["StoreError"] > 0


def test_version_1_images_without_checksum_still_read(exact_original, tmp_path):
    """Stores written before the checksum existed stay readable (without that check)."""
    original = exact_original
    record = json.loads(OpenEXR.File(str(original["path"]), header_only=True).header()["mcdenoise"])
    del record["checksum"]
    old = tmp_path / "v1.exr"
    _rewrite(original["path"], old, header_fn=lambda h: {**h, "mcdenoise": json.dumps({**record, "version": 1})})
    arrays, rec = read_image(old)
    assert digest(arrays) == original["digest"] and rec["version"] == 1
    v2 = tmp_path / "v2.exr"
    _rewrite(original["path"], v2, header_fn=lambda h: {**h, "mcdenoise": json.dumps(record)})
    with pytest.raises(StoreError, match=r"v2\.exr: header record has no checksum"):
        read_image(v2)


@pytest.mark.parametrize("text", ["[" * 100_000 + "]" * 100_000, '{"a": ' * 50_000 + "1" + "}" * 50_000,
                                  "\udcff", "NaN", "\x00" * 10])
def test_pathological_json_is_a_store_error(tmp_path, text):
    """Deep nesting (RecursionError in the json module), bad encodings, bare constants."""
    root = tmp_path / "store"
    root.mkdir()
    (root / "dataset.json").write_bytes(text.encode("utf-8", "surrogateescape"))
    with pytest.raises(StoreError, match=r"dataset\.json"):
        Store(root).manifest()
