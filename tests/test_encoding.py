"""The compact store encoding (pipeline.exr, docs/store.md "Bytes per channel group"): every
encoded value within its stated bound, everything else exact, R, G, B the beauty's half view, and
old (exact version 2, compact version 3 without R, G, B) stores still read and verify."""
import json

import numpy as np
import OpenEXR
import pytest

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.config import ConfigError, load_config
from mcdenoise.pipeline.exr import (
    BEAUTY_TOLERANCE,
    MANTISSA_BITS,
    StoreError,
    beauty_view,
    checksum,
    read_header,
    read_image,
    round_mantissa,
    scan_exr,
    store_encoding,
    write_image,
)
from mcdenoise.pipeline.store import Store, sha256
from mcdenoise.pipeline.verify import verify_store
from tests.helpers import make_clean_store


def rendered_like(h=24, w=20, seed=0):
    """Buffers as a renderer leaves them: the beauty accumulated on its own in float32 (so it equals
    the sum of the components only to round-off), variances over many decades and exact zeros."""
    rng = np.random.default_rng(seed)
    out = {}
    for b in schema.BUFFERS:
        shape = (h, w, b.size)
        out[b.name] = (rng.lognormal(-1, 2, shape) if b.radiance or b.name == "depth" else rng.random(shape))
        out[b.name] = out[b.name].astype(np.float32)
        var = rng.lognormal(-12, 8, shape) * (rng.random(shape) > 0.2)
        out[schema.variance_name(b.name)] = np.minimum(var, 1e30).astype(np.float32)
    out["color"] = accumulated_beauty(out)
    return out


def accumulated_beauty(arrays):
    color = np.zeros(arrays["emission"].shape, np.float32)
    for name in reversed(schema.RADIANCE_COMPONENTS):   # float32, in another order than the reader's sum
        color = color + arrays[name]
    return color


def assert_within(back, exact, bound, key):
    err = np.abs(back.astype(np.float64) - exact)
    limit = bound * np.maximum(np.abs(exact.astype(np.float64)), 2.0 ** -126)
    assert np.all(err <= limit), f"{key}: max error / bound {np.max(err / limit):.3g}"


@pytest.mark.parametrize("bits", [0, 3, 7, 10, 22])
def test_round_mantissa_keeps_its_bound_over_the_whole_float32_range(bits):
    rng = np.random.default_rng(bits)
    tiny = np.array([0.0, 1e-45, 3e-42, 1.17e-38, 1.1754942e-38], np.float32)
    huge = np.array([np.finfo(np.float32).max, 3.4e38, 1e38], np.float32)
    x = np.concatenate([tiny, huge, -huge, np.exp(rng.uniform(-100, 88, 20000)).astype(np.float32)])
    x = np.concatenate([x, -x[:100]])
    r = round_mantissa(x, bits)
    assert r.dtype == np.float32 and np.all(np.isfinite(r))
    assert not np.any(r.view(np.uint32) & np.uint32((1 << (23 - bits)) - 1)), "bits below the kept mantissa"
    assert_within(r, x, 2.0 ** -(bits + 1), f"{bits} bits")
    # the nearest representable value, not just any within the bound: rounding again changes nothing
    np.testing.assert_array_equal(round_mantissa(r, bits), r)
    np.testing.assert_array_equal(round_mantissa(x, 23), x)


def test_compact_round_trip_exact_or_within_the_stated_bounds(tmp_path):
    img = rendered_like()
    write_image(tmp_path / "exact.exr", img, encoding="exact")
    rec = write_image(tmp_path / "compact.exr", img, encoding="compact")
    exact, _ = read_image(tmp_path / "exact.exr")
    back, header = read_image(tmp_path / "compact.exr")
    assert header == rec and rec["version"] == 4
    assert rec["encoding"] == {"name": "compact", "beauty": "view", "mantissa_bits": MANTISSA_BITS, "compression": "ZIP"}
    assert back.keys() == exact.keys()
    for b in schema.BUFFERS:
        var = schema.variance_name(b.name)
        assert_within(back[var], img[var], 2.0 ** -(MANTISSA_BITS["variance"] + 1), var)
        assert np.count_nonzero(back[var] == 0) == np.count_nonzero(img[var] == 0)
        if b.name == "depth":
            assert_within(back[b.name], img[b.name], 2.0 ** -(MANTISSA_BITS["depth"] + 1), b.name)
        elif b.name != "color":   # radiance components float32, features in their half: as the exact encoding
            np.testing.assert_array_equal(back[b.name], exact[b.name], err_msg=b.name)
    np.testing.assert_array_equal(exact["color"], img["color"])
    assert not np.array_equal(back["color"], img["color"])    # the beauty really is derived here
    magnitude = sum(np.abs(img[n].astype(np.float64)) for n in schema.RADIANCE_COMPONENTS)
    assert np.all(np.abs(back["color"].astype(np.float64) - img["color"]) <= BEAUTY_TOLERANCE * magnitude)
    info = scan_exr(tmp_path / "compact.exr")
    assert info["compression"] == "ZIP" and all(info["channels"][c] == np.float16 for c in "RGB")
    with OpenEXR.File(str(tmp_path / "compact.exr"), separate_channels=True) as f:
        view = np.stack([f.channels()[c].pixels for c in "RGB"], axis=2)
    np.testing.assert_array_equal(view, beauty_view(back["color"]))       # the view of the exact derived beauty
    assert info["channels"]["variance.R"] == np.float32 and info["channels"]["depth.Z"] == np.float32
    assert scan_exr(tmp_path / "exact.exr")["compression"] == "ZIP"
    assert (tmp_path / "compact.exr").stat().st_size < (tmp_path / "exact.exr").stat().st_size
    # a reader asking for the beauty alone gets the same derived beauty
    alone, _ = read_image(tmp_path / "compact.exr", ["color"])
    assert list(alone) == ["color", "color.variance"]
    np.testing.assert_array_equal(alone["color"], back["color"])


def test_compact_zstd_holds_the_same_values_with_zstd(tmp_path):
    """render.encoding=compact-zstd: the compact values, ZSTD-compressed (OpenEXR >= 3.5 reads it); an image
    of a compact store written before ZIP was the default (no 'compression' in its record) is ZSTD too."""
    img = rendered_like()
    rec = write_image(tmp_path / "zip.exr", img, encoding="compact")
    zrec = write_image(tmp_path / "zstd.exr", img, encoding="compact-zstd")
    assert zrec["encoding"] == {**rec["encoding"], "compression": "ZSTD"}
    assert scan_exr(tmp_path / "zstd.exr")["compression"] == "ZSTD"
    a, b = read_image(tmp_path / "zip.exr")[0], read_image(tmp_path / "zstd.exr")[0]
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    assert [store_encoding(r) for r in (rec, zrec)] == ["compact", "compact-zstd"]
    old = {**zrec, "encoding": {k: v for k, v in zrec["encoding"].items() if k != "compression"}}
    assert store_encoding(old) == "compact-zstd" and store_encoding({"version": 2}) == "exact"
    with pytest.raises(StoreError, match=r"a\.exr: compression 'DWAA' is not a lossless EXR compression"):
        write_image(tmp_path / "a.exr", img, encoding="compact", compression="DWAA")
    assert not (tmp_path / "a.exr").exists()


def test_beauty_that_is_not_the_sum_of_its_components_is_stored_exactly(tmp_path):
    img = rendered_like()
    img["color"][3, 4, 1] *= 1 + 8 * BEAUTY_TOLERANCE       # one pixel off by more than round-off
    rec = write_image(tmp_path / "a.exr", img, encoding="compact")
    back, _ = read_image(tmp_path / "a.exr")
    assert rec["encoding"]["beauty"] == "stored" and "R" in scan_exr(tmp_path / "a.exr")["channels"]
    np.testing.assert_array_equal(back["color"], img["color"])
    # an image without the components (GT_clean, a denoiser's output) keeps its beauty too
    only = {"color": img["color"], "color.variance": np.zeros_like(img["color"])}
    assert write_image(tmp_path / "b.exr", only, encoding="compact")["encoding"]["beauty"] == "stored"
    np.testing.assert_array_equal(read_image(tmp_path / "b.exr")[0]["color"], img["color"])


def test_constant_channels_and_pruned_features_in_the_compact_encoding(tmp_path):
    img = rendered_like()
    for name in ("emission", "emission.variance"):
        img[name][:] = 0                       # no emitter in view
    img["color"] = accumulated_beauty(img)
    img["depth.variance"][:] = 0.1             # constant, rounded like the stored values would be
    del img["metallic"], img["metallic.variance"]
    rec = write_image(tmp_path / "a.exr", img, constants={"metallic": 0.0, "metallic.variance": 1 / 3},
                      encoding="compact")
    back, _ = read_image(tmp_path / "a.exr")
    assert rec["encoding"]["beauty"] == "view" and "emission.R" in rec["constants"]
    assert back["depth.variance"][0, 0, 0] == round_mantissa(np.float32([0.1]), MANTISSA_BITS["variance"])[0]
    assert_within(back["metallic.variance"], np.float32([[[1 / 3]]]), 2.0 ** -(MANTISSA_BITS["variance"] + 1),
                  "metallic.variance")
    assert np.all(back["emission"] == 0)


def test_inconsistent_compact_header_is_refused(tmp_path):
    write_image(tmp_path / "a.exr", rendered_like(), encoding="compact")
    with OpenEXR.File(str(tmp_path / "a.exr"), separate_channels=True) as f:
        chans = {k: v.pixels.copy() for k, v in f.channels().items()}
        record = json.loads(f.header()["mcdenoise"])
    for change, message in ((lambda r: r["encoding"].update(name="tiny"), "header record 'encoding' is"),
                            (lambda r: r.pop("encoding"), "header record 'encoding' is None"),
                            (lambda r: r["buffers"].remove("specular_direct"), "buffers specular_direct are not listed")):
        bad = json.loads(json.dumps(record))
        change(bad)
        with OpenEXR.File({"compression": OpenEXR.ZSTD_COMPRESSION, "mcdenoise": json.dumps(bad)}, dict(chans)) as f:
            f.write(str(tmp_path / "bad.exr"))
        with pytest.raises(StoreError, match=r"bad\.exr: .*" + message):
            read_header(tmp_path / "bad.exr")


def as_format_version_3(path, out):
    """Rewrite a compact (version 4, ``beauty: view``) image at ``out`` as the compact writer wrote it before
    the view existed: no R, G, B, a version 3 record with ``beauty: sum``, its checksum, ZIP."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        chans = {k: v.pixels.copy() for k, v in f.channels().items() if k not in ("R", "G", "B")}
        record = json.loads(f.header()["mcdenoise"])
    assert record["encoding"]["beauty"] == "view"
    record.update(version=3, encoding={**record["encoding"], "beauty": "sum"})
    record["checksum"] = checksum(record, chans)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                       "mcdenoise": json.dumps(record, sort_keys=True)}, chans) as f:
        f.write(str(out))
    return record


def test_exact_and_stored_beauties_are_real_channels_even_when_constant(tmp_path):
    """Every image shows its picture: a constant beauty (a black frame, an empty environment) is stored as R, G,
    B in each encoding, float32, and reads as the same constant it used to be restored from."""
    img = rendered_like()
    for name in ("color", *schema.RADIANCE_COMPONENTS):
        img[name][:] = 0.0
    img["emission"][:] = 0.25
    img["color"][:] = 0.25
    for encoding, beauty in (("exact", "stored"), ("compact", "view")):
        rec = write_image(tmp_path / f"{encoding}.exr", img, encoding=encoding)
        assert "R" not in rec["constants"] and rec.get("encoding", {"beauty": "stored"})["beauty"] == beauty
        assert {"R", "G", "B"} <= set(scan_exr(tmp_path / f"{encoding}.exr")["channels"])
        assert np.all(read_image(tmp_path / f"{encoding}.exr")[0]["color"] == np.float32(0.25))
    only = {"color": np.zeros_like(img["color"]), "color.variance": np.zeros_like(img["color"])}   # gt_clean-like
    rec = write_image(tmp_path / "black.exr", only, encoding="compact")
    assert rec["encoding"]["beauty"] == "stored" and set(rec["constants"]) == {"variance.R", "variance.G", "variance.B"}
    assert {c: t.name for c, t in scan_exr(tmp_path / "black.exr")["channels"].items()} == dict.fromkeys("RGB", "float32")


def test_compact_images_of_format_version_3_read_as_before(tmp_path):
    """A compact store written before the view (version 3, ``beauty: sum``, no R, G, B) reads what the same
    image written today reads, bit for bit, and verifies; a version 3 record cannot claim a view."""
    img = rendered_like()
    rec = write_image(tmp_path / "new.exr", img, encoding="compact")
    old = as_format_version_3(tmp_path / "new.exr", tmp_path / "old.exr")
    assert not {"R", "G", "B"} & set(scan_exr(tmp_path / "old.exr")["channels"])
    a, ra = read_image(tmp_path / "new.exr")
    b, rb = read_image(tmp_path / "old.exr")
    assert (ra, rb) == (rec, old) and a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k].view(np.uint32), b[k].view(np.uint32), err_msg=k)
    # a whole store: its images rewritten with beauties that are the sums of their components (views), then as
    # version 3; the pooled reads are the same, and verify passes both
    root = make_clean_store(tmp_path / "store", encoding="compact")
    store = Store(root)
    keys = store.frames()
    for key in keys:
        frame = store.frame_record(key.scene, key.frame)
        for image, record in frame["images"].items():
            arrays, header = store.read_image(key.scene, key.frame, image)
            arrays["color"] = schema.beauty_from_components(arrays)
            meta = {k: header[k] for k in ("image", "scene", "frame")}
            frame["images"][image] = store.write_image(key.scene, key.frame, image, arrays, meta=meta)
            assert frame["images"][image]["encoding"]["beauty"] == "view"
        store.write_frame_record(key.scene, key.frame, frame)
    assert verify_store(root).problems == []
    before = {key: store.read(key.scene, key.frame, spp=8) for key in keys}
    for key in keys:
        frame = store.frame_record(key.scene, key.frame)
        for image in frame["images"]:
            path = store.image_path(key.scene, key.frame, image)
            record = as_format_version_3(path, path)
            frame["images"][image] = {**record, "bytes": path.stat().st_size, "sha256": sha256(path)}
        store.write_frame_record(key.scene, key.frame, frame)
        after = store.read(key.scene, key.frame, spp=8)
        assert after.keys() == before[key].keys()
        for k in after:
            np.testing.assert_array_equal(after[k].view(np.uint32), before[key][k].view(np.uint32), err_msg=k)
    assert verify_store(root).problems == []
    bad = {**old, "version": 3, "encoding": {**old["encoding"], "beauty": "view"}}
    with OpenEXR.File(str(tmp_path / "new.exr"), separate_channels=True) as f:
        chans = {k: v.pixels.copy() for k, v in f.channels().items()}
    bad["checksum"] = checksum(bad, chans)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "mcdenoise": json.dumps(bad)}, chans) as f:
        f.write(str(tmp_path / "bad.exr"))
    with pytest.raises(StoreError, match=r"bad\.exr: header record 'encoding' is .*'beauty': 'sum' or 'stored'"):
        read_header(tmp_path / "bad.exr")


def test_a_view_that_is_not_the_derived_beauty_is_refused(tmp_path):
    """The view R, G, B must be the half view of the beauty the reader derives (an edited file whose checksum
    was redone, or a writer's mistake) and must be half; a stored beauty must be float32."""
    write_image(tmp_path / "a.exr", rendered_like(), encoding="compact")
    with OpenEXR.File(str(tmp_path / "a.exr"), separate_channels=True) as f:
        good = {k: v.pixels.copy() for k, v in f.channels().items()}
        record = json.loads(f.header()["mcdenoise"])

    def rewrite(chans, rec=record):
        rec = {**rec, "checksum": checksum(rec, chans)}
        with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "mcdenoise": json.dumps(rec)}, chans) as f:
            f.write(str(tmp_path / "bad.exr"))

    edited = {**good, "G": good["G"].copy()}
    edited["G"][2, 3] = np.float16(7.0)
    rewrite(edited)
    with pytest.raises(StoreError, match=r"bad\.exr: channels R, G, B \(the beauty's half view\) differ from the beauty "
                                         r"derived from the components in 1 values"):
        read_image(tmp_path / "bad.exr")
    assert read_image(tmp_path / "bad.exr", ["albedo"])[0].keys() == {"albedo", "albedo.variance"}
    rewrite({**good, "R": good["R"].astype(np.float32)})
    with pytest.raises(StoreError, match=r"bad\.exr: the beauty is marked as derived .* but channel R is float32, "
                                         r"expected float16"):
        read_header(tmp_path / "bad.exr")
    rewrite({k: v for k, v in good.items() if k != "B"})
    with pytest.raises(StoreError, match=r"but channel B is missing, expected float16"):
        read_header(tmp_path / "bad.exr")
    rewrite(good, {**record, "encoding": {**record["encoding"], "beauty": "stored"}})
    with pytest.raises(StoreError, match=r"the beauty is stored exactly, but channel R is float16, G is float16, "
                                         r"B is float16, expected float32"):
        read_header(tmp_path / "bad.exr")


def test_old_format_store_still_reads_and_verifies(tmp_path):
    """A store written the old way (every value exact, ZIP, version 2 records) reads as before and
    gives what the compact store of the same data gives, within the compact encoding's bounds."""
    old = Store(make_clean_store(tmp_path / "old", encoding="exact"))
    new = Store(make_clean_store(tmp_path / "new", encoding="compact"))
    assert verify_store(old.root).problems == [] and verify_store(new.root).problems == []
    for key in old.frames():
        for image in ("gt1", "s01"):
            rec = old.image_header(key.scene, key.frame, image)
            assert rec["version"] == 2 and "encoding" not in rec
            assert scan_exr(old.image_path(key.scene, key.frame, image))["compression"] == "ZIP"
        a, b = old.read(key.scene, key.frame, spp=8), new.read(key.scene, key.frame, spp=8)
        for k in a:
            bound = 2.0 ** -(MANTISSA_BITS["variance" if k.endswith(".variance") else "depth"] + 1)
            if k.endswith(".variance") or k == "depth":
                assert_within(b[k], a[k], 3 * bound, k)       # pooling two stacks adds float32 round-off
            else:
                np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_rendered_store_is_compact_and_derives_every_beauty(tiny_store):
    """The dataset stage writes the compact encoding, and real renders meet the beauty tolerance (so every
    image stores the half view and derives the exact beauty)."""
    store = Store(tiny_store[0])
    for key in store.frames():
        for image in store.frame_record(key.scene, key.frame)["images"]:
            rec = store.image_header(key.scene, key.frame, image)
            assert rec["version"] == 4 and rec["encoding"]["beauty"] == "view", f"{key}/{image}"


def test_encoding_config_key():
    assert load_config(None).render.encoding == "compact"
    assert load_config(None, ["render.encoding=exact"]).render.encoding == "exact"
    assert load_config(None, ["render.encoding=compact-zstd"]).render.encoding == "compact-zstd"
    with pytest.raises(ConfigError, match=r"render\.encoding: expected 'compact', 'compact-zstd' or 'exact', got 'zip'"):
        load_config(None, ["render.encoding=zip"])


def test_bytes_per_channel_group(tmp_path):
    """``verify STORE --bytes N``: per frame, the files' true sizes, and each group's bytes."""
    from mcdenoise.pipeline.verify import GROUPS, measure_bytes
    from tests.helpers import cli
    root = make_clean_store(tmp_path / "old", encoding="exact")
    result = measure_bytes(root, frames=2)
    store = Store(root)
    keys = store.frames()
    picked = [keys[0], keys[-1]]
    assert result["frames"] == 2
    assert result["stored"]["files"] == [sum(r["bytes"] for r in store.frame_record(k.scene, k.frame)["images"].values())
                                         for k in picked]
    stored, compact = result["stored"]["groups"], result["compact"]["groups"]
    assert set(stored) == set(GROUPS)
    # the synthetic features are constant (left out); everything with pixel data counts
    assert stored["features (half)"] == 0 and compact["features (half)"] == 0
    for group in ("beauty", "beauty variance", "radiance components", "depth"):
        assert stored[group] > 0 and compact[group] > 0, group
    table = cli("verify", root, "--bytes", "2").stdout
    assert "| **files (mean)** |" in table and table.count("\n| ") == 2 + len(GROUPS) + 2   # head, rule, groups, totals


def test_encodings_are_measured_on_the_stores_frames(tmp_path):
    """``verify STORE --encodings N``: each encoding's bytes are those of the file ``write_image`` writes for
    it, and the table says which of them older OpenEXR reads."""
    from mcdenoise.pipeline.verify import ENCODING_CHOICES, encodings_table, measure_encodings
    root = make_clean_store(tmp_path / "s", encoding="exact")
    result = measure_encodings(root, frames=1, repeat=1)
    store = Store(root)
    key = store.frames()[0]
    expected = 0
    for name in store.frame_record(key.scene, key.frame)["images"]:
        arrays, header = read_image(store.image_path(key.scene, key.frame, name))
        meta = {k: v for k, v in header.items() if k in ("image", "scene", "frame", "spp", "seed")}
        expected += write_image(tmp_path / "x.exr", arrays, meta=meta, encoding="compact") and (tmp_path / "x.exr").stat().st_size
    assert result["frames"] == 1 and len(result) == 1 + len(ENCODING_CHOICES)
    assert result["compact (ZIP)"]["bytes"] == [expected]
    assert all(r["write_s"][0] > 0 and r["read_s"][0] > 0 for k, r in result.items() if k != "frames")
    table = encodings_table(result)
    assert "| compact (ZIP) (default) |" in table and "| compact-zstd (ZSTD) |" in table
    assert all(line.endswith("| no (OpenEXR >= 3.5) |") == ("ZSTD" in line) for line in table.splitlines()[4:])


def test_denoise_exr_of_a_store_image_reads_the_exact_beauty_not_the_view(tmp_path):
    """``read_layers`` (``denoise --exr``) on a compact store image returns what ``read_image`` does: the
    colour derived from the components, not the half view in R, G, B (nor, for version 3, nothing)."""
    from mcdenoise.pipeline.exr import read_layers
    write_image(tmp_path / "new.exr", rendered_like(), encoding="compact")
    as_format_version_3(tmp_path / "new.exr", tmp_path / "old.exr")
    exact = read_image(tmp_path / "new.exr")[0]
    for name in ("new.exr", "old.exr"):
        layers = read_layers(tmp_path / name)
        assert layers.keys() == exact.keys()
        assert all(np.array_equal(layers[k], exact[k]) for k in exact), name


def test_read_layers_keeps_the_buffers_an_exact_image_records_as_constants(tmp_path):
    """An exact-encoded image whose emission is 0 everywhere records it as a constant (no channels): ``read_layers``
    (``denoise --exr``/``--sequence``) gives it back, so the frame still has every light component."""
    from mcdenoise.pipeline.exr import read_layers
    arrays = rendered_like()
    arrays["emission"] = np.zeros_like(arrays["emission"])
    arrays["emission.variance"] = np.zeros_like(arrays["emission.variance"])
    arrays["color"] = accumulated_beauty(arrays)
    write_image(tmp_path / "x.exr", arrays)
    assert "emission.R" in read_header(tmp_path / "x.exr")["constants"]      # no channel holds it
    layers = read_layers(tmp_path / "x.exr")
    exact = read_image(tmp_path / "x.exr")[0]
    assert "emission" in layers and not layers["emission"].any()
    assert layers.keys() == exact.keys() and all(np.array_equal(layers[k], exact[k]) for k in exact)
