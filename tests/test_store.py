"""The EXR store: round trips, omitted constants, stack combination, clear errors on bad files."""
import json

import numpy as np
import OpenEXR
import pytest

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.exr import StoreError, read_header, read_image, write_image
from mcdenoise.pipeline.store import FrameKey, Store, combine_stacks, image_seed


def random_image(h=12, w=10, seed=0):
    rng = np.random.default_rng(seed)
    out = {}
    for b in schema.BUFFERS:
        out[b.name] = rng.random((h, w, b.size)).astype(np.float32) * 3
        out[schema.variance_name(b.name)] = rng.random((h, w, b.size)).astype(np.float32) * 1e-8
    return out


def test_round_trip_keeps_float32_radiance_and_variance_exactly(tmp_path):
    img = random_image()
    write_image(tmp_path / "a.exr", img)
    back, rec = read_image(tmp_path / "a.exr")
    for b in schema.BUFFERS:
        var = schema.variance_name(b.name)
        # variance in float32 (tiny values survive; half would flush 1e-8 to zero)
        np.testing.assert_array_equal(back[var], img[var])
        if b.dtype == np.float32:
            np.testing.assert_array_equal(back[b.name], img[b.name])
        else:  # features in half precision
            np.testing.assert_allclose(back[b.name], img[b.name], rtol=1e-3, atol=1e-3)
        assert back[b.name].dtype == np.float32


def test_storage_types_on_disk(tmp_path):
    write_image(tmp_path / "a.exr", random_image())
    with OpenEXR.File(str(tmp_path / "a.exr"), separate_channels=True) as f:
        chans = {k: v.pixels for k, v in f.channels().items()}
        assert f.header()["compression"] == OpenEXR.ZIP_COMPRESSION
    assert chans["R"].dtype == np.float32
    assert chans["variance.R"].dtype == np.float32
    assert chans["diffuse_direct.G"].dtype == np.float32
    assert chans["albedo.variance.B"].dtype == np.float32
    assert chans["N.X"].dtype == np.float16
    assert chans["depth.Z"].dtype == np.float32


def test_constant_channels_are_omitted_and_restored_exactly(tmp_path):
    img = random_image()
    img["metallic"][:] = 0.3          # constant, stored as half: restored as half-rounded 0.3
    img["metallic.variance"][:] = 0
    img["emission"][..., 1] = 2.5    # one constant channel of an RGB layer
    write_image(tmp_path / "a.exr", img)
    write_image(tmp_path / "b.exr", img, omit_constant=False)
    with OpenEXR.File(str(tmp_path / "a.exr"), separate_channels=True) as f:
        names = set(f.channels())
    assert "metallic.Y" not in names and "metallic.variance.Y" not in names and "emission.G" not in names
    assert "emission.R" in names
    a, rec = read_image(tmp_path / "a.exr")
    b, _ = read_image(tmp_path / "b.exr")
    assert rec["constants"]["emission.G"] == 2.5
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert (tmp_path / "a.exr").stat().st_size < (tmp_path / "b.exr").stat().st_size


def test_pruned_features_written_as_constants(tmp_path):
    img = random_image()
    del img["transmission"], img["transmission.variance"]
    write_image(tmp_path / "a.exr", img, constants={"transmission": 0.0, "transmission.variance": 0.0})
    back, rec = read_image(tmp_path / "a.exr")
    assert np.all(back["transmission"] == 0) and back["transmission"].shape == (12, 10, 1)
    assert rec["constants"]["transmission.Y"] == 0.0


def test_writer_refuses_nonfinite(tmp_path):
    img = random_image()
    img["color"][0, 0, 0] = np.nan
    with pytest.raises(StoreError, match="'color' has non-finite"):
        write_image(tmp_path / "a.exr", img)
    assert list(tmp_path.iterdir()) == []   # no partial or temporary file left behind


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
    img = random_image()

    class Boom(OpenEXR.File):
        def write(self, path):
            with open(path, "wb") as f:
                f.write(b"partial")
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(OpenEXR, "File", Boom)
    with pytest.raises(OSError, match="No space"):
        write_image(tmp_path / "a.exr", img)
    assert list(tmp_path.iterdir()) == []


def test_truncated_exr_is_a_clear_error(tmp_path):
    write_image(tmp_path / "a.exr", random_image())
    data = (tmp_path / "a.exr").read_bytes()
    (tmp_path / "t.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(StoreError, match=r"t\.exr: corrupt or truncated"):
        read_image(tmp_path / "t.exr")


def test_not_an_exr_is_a_clear_error(tmp_path):
    (tmp_path / "x.exr").write_bytes(b"hello world")
    with pytest.raises(StoreError, match=r"x\.exr: not an OpenEXR file"):
        read_image(tmp_path / "x.exr")


def test_missing_channel_names_the_channel(tmp_path):
    img = random_image()
    write_image(tmp_path / "a.exr", img, omit_constant=False)
    with OpenEXR.File(str(tmp_path / "a.exr"), separate_channels=True) as f:
        header = dict(f.header())
        chans = {k: v.pixels for k, v in f.channels().items() if k != "albedo.G"}
    with OpenEXR.File({k: header[k] for k in ("compression", "type", "mcdenoise")}, chans) as f:
        f.write(str(tmp_path / "m.exr"))
    with pytest.raises(StoreError, match=r"m\.exr: channel 'albedo\.G' of buffer 'albedo' is missing"):
        read_image(tmp_path / "m.exr")


def test_wrong_dtype_names_the_channel(tmp_path):
    img = random_image()
    write_image(tmp_path / "a.exr", img, omit_constant=False)
    with OpenEXR.File(str(tmp_path / "a.exr"), separate_channels=True) as f:
        header = dict(f.header())
        chans = {k: v.pixels for k, v in f.channels().items()}
    chans["variance.R"] = chans["variance.R"].astype(np.float16)
    with OpenEXR.File({k: header[k] for k in ("compression", "type", "mcdenoise")}, chans) as f:
        f.write(str(tmp_path / "d.exr"))
    with pytest.raises(StoreError, match=r"channel 'variance\.R' is float16, expected float32"):
        read_image(tmp_path / "d.exr")


def test_foreign_exr_without_our_header(tmp_path):
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"R": np.zeros((4, 4), np.float32)}) as f:
        f.write(str(tmp_path / "f.exr"))
    with pytest.raises(StoreError, match="not an image written by this pipeline"):
        read_header(tmp_path / "f.exr")


def test_combine_stacks_equals_pooled_samples():
    """The combined variance must equal what one render of all K·n samples reports."""
    rng = np.random.default_rng(1)
    K, n, h, w = 4, 4, 5, 6
    samples = rng.gamma(0.5, 2.0, size=(K, n, h, w, 3))   # heavy-ish tailed, like MC radiance
    stacks = []
    for k in range(K):
        s = samples[k]
        stacks.append({"color": s.mean(0).astype(np.float32),
                       "color.variance": (s.var(0, ddof=1) / n).astype(np.float32)})
    out = combine_stacks(stacks, n)
    allsamp = samples.reshape(K * n, h, w, 3)
    np.testing.assert_allclose(out["color"], allsamp.mean(0), rtol=1e-5)
    np.testing.assert_allclose(out["color.variance"], allsamp.var(0, ddof=1) / (K * n), rtol=1e-4)


def test_combine_stacks_unequal_counts_equals_pooled_samples():
    """Estimates of 12, 4 and 1 samples (a progressive GT pools its running estimate with each
    new pass): mean and variance of the mean equal those of the 17 samples taken together."""
    rng = np.random.default_rng(2)
    counts, h, w = [12, 4, 1], 3, 4
    samples = rng.gamma(0.5, 2.0, size=(sum(counts), h, w, 3))
    parts, lo = [], 0
    for n in counts:
        s = samples[lo:lo + n]
        lo += n
        var = s.var(0, ddof=1) / n if n > 1 else np.zeros_like(s[0])
        parts.append({"color": s.mean(0).astype(np.float32), "color.variance": var.astype(np.float32)})
    out = combine_stacks(parts, counts)
    np.testing.assert_allclose(out["color"], samples.mean(0), rtol=1e-5)
    np.testing.assert_allclose(out["color.variance"], samples.var(0, ddof=1) / len(samples), rtol=1e-4)
    with pytest.raises(ValueError, match="3 stacks but 2 sample counts"):
        combine_stacks(parts, counts[:2])


def test_image_seeds_are_distinct():
    frames, images = 8, 18
    seeds = {image_seed(3, s, f, i, frames, images) for s in range(300) for f in range(frames) for i in range(images)}
    assert len(seeds) == 300 * frames * images


def test_store_read_averages_stacks(tmp_path):
    store = Store(tmp_path)
    store.write_scene_manifest("s0", {"frames": 1, "stack_spp": 4, "stacks": 4, "gt_spp": 64})
    imgs = [random_image(seed=k) for k in range(4)]
    for k, img in enumerate(imgs):
        store.write_image("s0", 0, f"s{k:02d}", img)
    both = store.read("s0", 0, 8, stacks=[1, 3])
    np.testing.assert_allclose(both["color"], (imgs[1]["color"] + imgs[3]["color"]) / 2, rtol=1e-6)
    one = store.read("s0", 0, 4, rng=np.random.default_rng(0))
    assert one["color"].shape == (12, 10, 3)
    with pytest.raises(StoreError, match="spp 6 is not a multiple"):
        store.read("s0", 0, 6)


def test_frames_with_lists_the_frames_that_have_the_images(tmp_path):
    store = Store(tmp_path)
    store.write_manifest({"scenes": ["s0", "s1"], "splits": {"train": ["s0"], "val": ["s1"]}})
    for scene in ("s0", "s1"):
        store.write_scene_manifest(scene, {"frames": 2, "stack_spp": 4, "stacks": 1, "gt_spp": 64})
    store.write_image("s0", 1, "gt_clean", random_image())
    store.write_image("s0", 0, "s00", random_image())
    store.write_image("s0", 1, "s00", random_image())
    assert store.frames_with("train") == [FrameKey("s0", 1)]
    assert store.frames_with("train", ["s00"]) == [FrameKey("s0", 0), FrameKey("s0", 1)]
    assert store.frames_with("train", ["s00", "gt_clean"]) == [FrameKey("s0", 1)]
    assert store.frames_with("val") == []
    assert store.frames_with("test") == []        # a split the store does not have: no frames


def test_malformed_manifest_is_a_clear_error(tmp_path):
    (tmp_path / "dataset.json").write_text("{not json")
    with pytest.raises(StoreError, match=r"dataset\.json: dataset manifest is not valid JSON"):
        Store(tmp_path).manifest()
    (tmp_path / "dataset.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(StoreError, match="not a mcdenoise-store manifest"):
        Store(tmp_path).manifest()
