"""Fuzzing the store's readers with damaged files (hypothesis, derandomized for CI).

Every damaged EXR (truncated, bit-flipped, header bytes overwritten, header fields patched to
absurd values, channels renamed or retyped, the ``mcdenoise`` record mutated) must give either a
``StoreError`` or a read that returns exactly the original data; anything else (another
exception, a native crash, a hang, different data) fails the test. The reads run in a separate
reader process with a time limit per case, so a native crash in OpenEXR or a hang is observed as
such instead of killing pytest. Malformed manifests (dataset.json, scene.json, frame.json) go
through the Store API in process (pure Python): StoreError or a valid answer.

TZA blobs (OIDN's weights), trained model folders (model.json + safetensors) and config files are
fuzzed in process (pure Python readers; a few thousand cases a second): a clean one-line error (a
``PipelineError``), or a read that is right by that reader's own standard (see each test).

Each test prints how many cases ran and how they ended; ``tests/conftest.py`` prints the totals
per reader at the end of the run (inputs, clean errors, correct reads, crashes, silent wrong reads).
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
from tests.helpers import FUZZ_TOTALS, all_keys

ROOT = Path(__file__).resolve().parents[1]
TINY_CONFIG = ROOT / "configs" / "tiny.yaml"
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

    def report(self, capsys, reader: str = "EXR images (headers, records, channels, pixels)") -> None:
        with capsys.disabled():
            total = sum(self.counts.values())
            print(f"\nfuzz {self.name}: {total} cases: " + ", ".join(f"{k} {v}" for k, v in sorted(self.counts.items())))
        record_totals(reader, self.counts)
        assert not self.failures, "\n".join(self.failures[:10])
        assert self.counts["StoreError"] > 0


OUTCOMES = {"StoreError": "clean error", "clean error": "clean error", "correct read": "correct read",
            "valid answer": "valid answer", "WRONG DATA": "wrong read", "wrong read": "wrong read"}


def record_totals(reader: str, counts: Counter) -> None:
    """Add a test's outcomes to the run's totals (printed by tests/conftest.py): a clean one-line error, a
    correct read, a valid answer; anything else (another exception, a native crash, a hang) is a crash."""
    totals = FUZZ_TOTALS.setdefault(reader, {})
    for outcome, n in counts.items():
        key = OUTCOMES.get(outcome, "crash")
        totals[key] = totals.get(key, 0) + n


def _case(tmp_path: Path, data: bytes) -> Path:
    path = tmp_path / "case.exr"
    path.write_bytes(data)
    return path


# ---- EXR mutations -----------------------------------------------------------------------------

@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


def _exercise(store: Store) -> set[str]:
    """What the stages ask of a store; the digests of the pixels it served."""
    served = set()
    for key in store.frames():
        store.is_frame_complete(key.scene, key.frame, ["s00"])
        rec = store.frame_record(key.scene, key.frame)
        if rec is not None:
            served.add(digest(store.read(key.scene, key.frame, 4)))
    return served


@pytest.mark.slow
def test_fuzz_manifests(tmp_path_factory, capsys):
    tally = Counter()
    failures = []
    root = tmp_path_factory.mktemp("manifests") / "store"
    _good_store(root)
    files = {"dataset.json": root / "dataset.json", "scene.json": root / "scenes/s0/scene.json",
             "frame.json": root / "scenes/s0/000/frame.json"}
    originals = {k: p.read_bytes() for k, p in files.items()}
    pixels = _exercise(Store(root))
    assert len(pixels) == 1

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
            served = _exercise(Store(root))
            if served <= pixels:          # a manifest may hide a frame, never serve other pixels
                tally["valid answer"] += 1
            else:
                tally["wrong read"] += 1
                failures.append(f"{which} {mutation!r}: served pixels that are not the frame's")
        except StoreError:
            tally["StoreError"] += 1
        except Exception as exc:  # noqa: BLE001
            tally[type(exc).__name__] += 1
            failures.append(f"{which} {mutation!r}: {type(exc).__name__}: {exc}")

    case()
    with capsys.disabled():
        print(f"\nfuzz manifests: {sum(tally.values())} cases: " + ", ".join(f"{k} {v}" for k, v in sorted(tally.items())))
    record_totals("store manifests (dataset.json, scene.json, frame.json)", tally)
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


# ---- in-process readers: TZA blobs, model folders, config files ---------------------------------
# Pure Python (struct, safetensors' Rust parser, PyYAML), so the cases run in this process: a few
# thousand a second. Each counts as a clean one-line error (a PipelineError subclass), a correct
# read or a valid answer (defined per reader); anything else fails the test.

INPROC = settings(FUZZ, max_examples=800)


def damage(data: bytes):
    """A strategy of damaged copies of ``data``: truncated, bits flipped, bytes overwritten, bytes appended."""
    n = len(data)

    def flip(bits):
        buf = bytearray(data)
        for b in bits:
            buf[b // 8] ^= 1 << (b % 8)
        return bytes(buf)

    def over(pos, junk):
        buf = bytearray(data)
        buf[pos:pos + len(junk)] = junk
        return bytes(buf[:n])

    return st.one_of(st.integers(0, n - 1).map(lambda k: data[:k]),
                     st.lists(st.integers(0, n * 8 - 1), min_size=1, max_size=4, unique=True).map(flip),
                     st.tuples(st.integers(0, n - 1), st.binary(min_size=1, max_size=8)).map(lambda a: over(*a)),
                     st.binary(min_size=1, max_size=16).map(lambda tail: data + tail))


class Outcomes:
    """Counts of one in-process fuzz test; ``failures`` say which input did what."""

    def __init__(self, reader: str):
        self.reader, self.counts, self.failures = reader, Counter(), []

    def run(self, label: str, read, judge) -> None:
        """``read()`` the input; ``judge(result)``: 'correct read' / 'valid answer', or a string saying why the
        result is wrong."""
        from mcdenoise.pipeline.errors import PipelineError
        try:
            result = read()
        except PipelineError as exc:
            self.counts["clean error"] += 1
            if "\n" in str(exc):
                self.failures.append(f"{label}: a {type(exc).__name__} of several lines: {exc!s:.300}")
            return
        except Exception as exc:  # noqa: BLE001 - counted and reported, the test fails on it
            self.counts["crash"] += 1
            self.failures.append(f"{label}: {type(exc).__name__}: {exc!s:.300}")
            return
        verdict = judge(result)
        if verdict in ("correct read", "valid answer"):
            self.counts[verdict] += 1
        else:
            self.counts["wrong read"] += 1
            self.failures.append(f"{label}: {verdict}")

    def report(self, capsys) -> None:
        with capsys.disabled():
            print(f"\nfuzz {self.reader}: {sum(self.counts.values())} cases: "
                  + ", ".join(f"{k} {v}" for k, v in sorted(self.counts.items())))
        record_totals(self.reader, self.counts)
        assert not self.failures, "\n".join(self.failures[:10])
        assert self.counts["clean error"] > 0


def _tza_original() -> bytes:
    from mcdenoise.pipeline.weights import TZATensor, write_tza
    rng = np.random.default_rng(3)
    return write_tza({"enc_conv0.weight": TZATensor(rng.standard_normal((4, 3, 3, 3)).astype(np.float16), "oihw"),
                      "enc_conv0.bias": TZATensor(rng.standard_normal(4).astype(np.float16), "x"),
                      "dec_conv0.weight": TZATensor(rng.standard_normal((3, 4, 1, 1)).astype(np.float32), "oihw"),
                      "scale": TZATensor(np.arange(5, dtype=np.int8), "x")})


def _tza_padding(tensors) -> list[tuple[int, int]]:
    """The byte ranges OIDN's layout pads with zeros (before each tensor's data and before the table)."""
    pos, gaps = 12, []
    for t in tensors.values():
        start = pos + (-pos % 64)
        gaps.append((pos, start))
        pos = start + t.array.nbytes
    gaps.append((pos, pos + (-pos % 64)))
    return gaps


def test_fuzz_tza_blobs(capsys):
    """OIDN weight archives: a TZAError (a WeightsError), or a faithful read: written back, the tensors
    give the same bytes but for the zero padding and the minor version (no byte misread, none ignored)."""
    from mcdenoise.pipeline.weights import TZA_VERSION, read_tza, write_tza
    original = _tza_original()
    assert write_tza(read_tza(original)) == original
    out = Outcomes("TZA blobs (pipeline/weights.py)")
    table = int.from_bytes(original[4:12], "little")

    def faithful(blob):
        def judge(tensors):
            again = bytearray(write_tza(tensors))
            given = bytearray(blob)
            if len(again) != len(given):
                return f"read {len(blob)} bytes as an archive of {len(again)}"
            for a, b in _tza_padding(tensors):
                given[a:b] = bytes(b - a)
            given[3] = TZA_VERSION[1]       # any 2.x minor version reads as 2.0 (the writer's)
            return "correct read" if again == given else "read as other tensors than the bytes hold"
        return judge

    # Damage anywhere, and damage aimed at the table (names, shapes, dtypes, offsets: where a lax
    # reader would read other bytes as weights).
    @INPROC
    @given(st.one_of(damage(original),
                     st.tuples(st.integers(table, len(original) - 1), st.binary(min_size=1, max_size=8))
                     .map(lambda a: original[:a[0]] + a[1] + original[a[0] + len(a[1]):])))
    def case(blob):
        out.run(f"{blob.hex()}", lambda: read_tza(blob, "case.tza"), faithful(blob))

    case()
    out.report(capsys)


@pytest.mark.slow
def test_fuzz_model_folders(tmp_path, capsys):
    """A trained model folder (model.json + model.safetensors, here a small Isik network) with either file
    damaged, or model.json's values replaced: a CheckpointError, or the model with exactly the trained
    weights (safetensors carries no checksum of its own; the CRC-32 in its metadata finds the damage)."""
    import torch

    from mcdenoise.clean.model import load_model
    from tests.helpers import save_untrained_isik

    folder = tmp_path / "isik"
    save_untrained_isik(folder)
    files = {"model.safetensors": folder / "model.safetensors", "model.json": folder / "model.json"}
    originals = {k: p.read_bytes() for k, p in files.items()}
    trained = {k: v.clone() for k, v in load_model(folder)[0].state_dict().items()}
    record = json.loads(originals["model.json"])
    out = Outcomes("model folders (model.json + safetensors)")

    def judge(result):
        state = result[0].state_dict()
        same = state.keys() == trained.keys() and all(torch.equal(state[k], trained[k]) for k in state)
        return "correct read" if same else "loaded other weights than the trained ones"

    @INPROC
    @given(st.one_of(st.tuples(st.just("model.safetensors"), damage(originals["model.safetensors"])),
                     st.tuples(st.just("model.json"), damage(originals["model.json"])),
                     st.tuples(st.just("model.json"), st.tuples(st.sampled_from(sorted(record)), json_values)
                               .map(lambda kv: json.dumps({**record, kv[0]: kv[1]}).encode()))))
    def case(change):
        which, data = change
        for k, p in files.items():
            p.write_bytes(data if k == which else originals[k])
        out.run(f"{which}: {data[:80]!r}", lambda: load_model(folder), judge)

    case()
    out.report(capsys)


def _subset_of(given, resolved) -> bool:
    """Every key and value of the YAML ``given`` is in the resolved config (numbers as numbers)."""
    if isinstance(given, dict):
        return isinstance(resolved, dict) and all(k in resolved and _subset_of(v, resolved[k]) for k, v in given.items())
    if isinstance(given, list):
        return isinstance(resolved, list) and len(given) == len(resolved) and all(map(_subset_of, given, resolved))
    if isinstance(resolved, float) and not isinstance(given, bool):
        try:
            g = float(given)
        except (TypeError, ValueError):
            return False
        return g == resolved or (g != g and resolved != resolved)
    return type(given) is type(resolved) and given == resolved


@pytest.mark.slow
def test_fuzz_config_files(tmp_path, capsys):
    """configs/tiny.yaml damaged as text, or with a key's value replaced: a ConfigError naming the file,
    or a config holding every key and value the file gives (none ignored, none read as another)."""
    import yaml

    from mcdenoise.pipeline.config import load_config, to_dict

    text = TINY_CONFIG.read_text()
    data = yaml.safe_load(text)
    paths = [(s, k) for s, v in data.items() if isinstance(v, dict) for k in v] + [(k, None) for k in data]
    path = tmp_path / "case.yaml"
    out = Outcomes("config files (YAML)")

    def judge(case_text):
        def check(cfg):
            given = yaml.safe_load(case_text) or {}      # an empty file: the defaults
            return "valid answer" if _subset_of(given, to_dict(cfg)) else "a key or value of the file was not used"
        return check

    def replaced(change):
        (section, key), value = change
        d = json.loads(json.dumps(data))
        if key is None:
            d[section] = value
        else:
            d[section][key] = value
        return yaml.safe_dump(d)

    @INPROC
    @given(st.one_of(damage(text.encode()).map(lambda b: b.decode("utf-8", "replace")),
                     st.tuples(st.sampled_from(paths), json_values).map(replaced)))
    def case(case_text):
        path.write_text(case_text)
        out.run(f"{case_text[:120]!r}", lambda: load_config(path), judge(case_text))

    case()
    out.report(capsys)


# ---- what the fuzzing found, one case each ----------------------------------------------------------

def test_tza_tensor_offset_off_oidn_layout_is_an_error():
    """A table entry pointing 64 bytes further (still inside the blob) once read other bytes as the weights."""
    from mcdenoise.pipeline.errors import WeightsError
    from mcdenoise.pipeline.weights import read_tza
    blob = bytearray(_tza_original())
    table = int.from_bytes(blob[4:12], "little")
    name = b"enc_conv0.bias"
    at = blob.index(name, table) + len(name) + 1 + 4 + 1 + 1      # ndims, shape, layout, dtype code
    offset = int.from_bytes(blob[at:at + 8], "little")
    blob[at:at + 8] = (offset + 64).to_bytes(8, "little")
    with pytest.raises(WeightsError, match=r"x\.tza: tensor 'enc_conv0\.bias' starts at byte \d+, expected \d+"):
        read_tza(bytes(blob), "x.tza")


def test_flipped_bit_in_saved_weights_is_a_checkpoint_error(tmp_path):
    import torch

    from mcdenoise.pipeline import weights
    from mcdenoise.pipeline.errors import CheckpointError
    weights.save(tmp_path, "affinity", {"w": torch.arange(16, dtype=torch.float32)}, {"hparams": {}})
    path = tmp_path / "model.safetensors"
    assert torch.equal(weights.load_tensors(path)["w"], torch.arange(16, dtype=torch.float32))
    data = bytearray(path.read_bytes())
    data[-5] ^= 0x01                                   # one bit of the last weight
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=r"model\.safetensors: damaged \(CRC-32 .*\); restore it or train it"):
        weights.load_tensors(path)


def test_saving_the_same_tensors_twice_gives_the_same_bytes(tmp_path):
    """safetensors orders metadata keys as a Rust HashMap does (anew each call); the header is rewritten sorted."""
    import torch

    from mcdenoise.pipeline.weights import save_safetensors
    tensors, meta = {"w": torch.ones(3)}, {"format": "f", "state": "{}", "z": "1", "a": "2"}
    for i in range(8):
        save_safetensors(tmp_path / f"{i}.safetensors", tensors, meta)
    assert len({(tmp_path / f"{i}.safetensors").read_bytes() for i in range(8)}) == 1


def test_yaml_error_and_a_range_of_non_numbers_are_one_line_config_errors(tmp_path):
    from mcdenoise.pipeline.config import ConfigError, load_config
    bad = tmp_path / "bad.yaml"
    bad.write_text("dataset:\n  scenes: 3\n stacks: [\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: not valid YAML \(line \d+, column \d+: ") as info:
        load_config(bad)
    assert "\n" not in str(info.value)
    bad.write_text("scene:\n  objects: [{}, []]\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: scene\.objects: expected a range \[min, max\]"):
        load_config(bad)
