"""What we write, opened by a reader other than our own: OpenImageIO (the pinned wheel of
requirements.lock), whose OpenEXR is older than 3.5, as in the Blender, Nuke and OpenImageIO builds
in use (docs/compatibility.md). Channel names and pixel values must be what this project's reader
sees, for a store frame, a `denoise` output, a black frame and a frame with NaN/Inf."""
import re

import numpy as np
import OpenEXR
import OpenImageIO as oiio
import pytest

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.exr import HALF_MAX, read_image, scan_exr, write_image
from mcdenoise.pipeline.store import Store
from tests.helpers import TINY, cli


def oiio_read(path) -> tuple[dict[str, np.ndarray], str]:
    """``{channel: HxW float32}`` and the compression, as OpenImageIO reads ``path``; AssertionError with
    its message when it cannot."""
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        assert pixels is not None and not inp.has_error, inp.geterror()
        return ({name: pixels[..., i] for i, name in enumerate(spec.channelnames)},
                str(spec.getattribute("compression")))
    finally:
        inp.close()


def openexr_channels(path) -> dict[str, np.ndarray]:
    """The channels stored in ``path`` as OpenEXR's Python binding (this project's reader) decodes them."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        return {name: ch.pixels.astype(np.float32) for name, ch in f.channels().items()}


def assert_same_channels(path) -> dict[str, np.ndarray]:
    """OpenImageIO sees every stored channel, with the stored values (half channels widened exactly)."""
    ours = openexr_channels(path)
    theirs, _ = oiio_read(path)
    assert sorted(theirs) == sorted(ours) == sorted(scan_exr(path)["channels"])
    for name, values in ours.items():
        np.testing.assert_array_equal(theirs[name], values, err_msg=name)
    return theirs


def test_the_pinned_reader_is_an_older_openexr():
    """The check means "OpenEXR before 3.5 reads it" only while the wheel's OpenEXR is older than 3.5."""
    version = re.search(r"OpenEXR (\d+)\.(\d+)", oiio.get_string_attribute("library_list"))
    assert version and (3, 0) <= (int(version[1]), int(version[2])) < (3, 5), oiio.get_string_attribute("library_list")


def assert_shows_the_beauty(path, beauty: np.ndarray, view: bool) -> None:
    """OpenImageIO lists R, G, B first and its pixels of them are the beauty our reader returns: within half
    precision (relative 2^-11, 2^-25 absolute below half's normal range, clamped to its range) for a compact
    image's view, exactly for a stored beauty."""
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    try:
        spec = inp.spec()
        assert list(spec.channelnames[:3]) == ["R", "G", "B"], spec.channelnames
        rgb = inp.read_image(0, 0, 0, 3, oiio.FLOAT)
    finally:
        inp.close()
    assert rgb.shape == beauty.shape and np.all(np.isfinite(rgb))
    if not view:
        np.testing.assert_array_equal(rgb, beauty)
        return
    exact = np.clip(beauty.astype(np.float64), -HALF_MAX, HALF_MAX)
    assert np.all(np.abs(rgb - exact) <= 2.0 ** -11 * np.abs(exact) + 2.0 ** -25)


def _frame_buffers(rng, h=12, w=16) -> dict[str, np.ndarray]:
    """Every buffer of a frame as the renderer leaves it: the beauty accumulated separately (float32), so it
    is the sum of the components to round-off only; radiance from 1e-7 to 1e5, fireflies past half's range."""
    out = {}
    for b in schema.BUFFERS:
        x = rng.lognormal(-1, 3, (h, w, b.size)) if b.radiance else rng.random((h, w, b.size))
        out[b.name] = x.astype(np.float32)
        out[schema.variance_name(b.name)] = (rng.random((h, w, b.size)) * 1e-2).astype(np.float32)
    out["diffuse_indirect"][2, 3] = 9e4
    color = np.zeros((h, w, 3), np.float32)
    for name in reversed(schema.RADIANCE_COMPONENTS):
        color = color + out[name]
    out["color"] = color
    return out


def test_every_store_image_shows_its_picture_in_openimageio(tmp_path):
    """The store's writer (compact, the default): a stack and a GT have R, G, B, the half view of the beauty,
    and our reader returns the exact beauty derived from the components; gt_clean (colour only) stores its
    beauty exactly, and a constant one too."""
    store = Store(tmp_path / "store")
    rng = np.random.default_rng(3)
    for image in ("s00", "gt1"):
        buffers = _frame_buffers(rng)
        record = store.write_image("s00000", 0, image, buffers, meta={"image": image})
        assert record["encoding"]["beauty"] == "view"
        path = store.image_path("s00000", 0, image)
        ours, _ = read_image(path)
        exact = schema.beauty_from_components(buffers)
        np.testing.assert_array_equal(ours["color"].view(np.uint32), exact.view(np.uint32))
        assert_shows_the_beauty(path, ours["color"], view=True)
        assert_same_channels(path)
    for name, hdr in (("gt_clean", _frame_buffers(rng)["color"]), ("black", np.zeros((12, 16, 3), np.float32))):
        record = store.write_image("s00000", 0, name, {"color": hdr, "color.variance": np.zeros_like(hdr)},
                                   meta={"image": name})
        path = store.image_path("s00000", 0, name)
        assert record["encoding"]["beauty"] == "stored"
        np.testing.assert_array_equal(read_image(path)[0]["color"], hdr)
        assert_shows_the_beauty(path, hdr, view=False)


@pytest.mark.slow
def test_store_frames_open_in_openimageio(tiny_store):
    """Every image of a rendered frame (the default compact encoding, ZIP) opens; each stored channel
    holds what our reader returns for it, and R, G, B show the beauty."""
    store = Store(tiny_store[0])
    key = store.frames()[0]
    for image in store.frame_record(key.scene, key.frame)["images"]:
        path = store.image_path(key.scene, key.frame, image)
        theirs = assert_same_channels(path)
        assert oiio_read(path)[1] == "zip"
        ours, record = read_image(path)
        assert record["encoding"]["beauty"] == "view"
        assert_shows_the_beauty(path, ours["color"], view=True)
        for c, ch in enumerate(("emission.R", "emission.G", "emission.B")):
            if ch in theirs:
                np.testing.assert_array_equal(theirs[ch], ours["emission"][..., c])
        assert {"diffuse_direct.R", "albedo.R", "N.X", "variance.R"} <= set(theirs), image


def test_zstd_is_what_older_openexr_cannot_read(tmp_path):
    """render.encoding=compact-zstd stays a choice, and this is why it is not the default."""
    rgb = np.ones((8, 8, 3), np.float32)
    write_image(tmp_path / "z.exr", {"color": rgb, "color.variance": rgb}, omit_constant=False,
                encoding="compact-zstd")
    with pytest.raises(AssertionError):
        oiio_read(tmp_path / "z.exr")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A black 16x16 frame (R, G, B zero; albedo and normal present) and a noisy one with NaN, +Inf and
    -Inf in its colour, written by OpenEXR directly (as another renderer would)."""
    folder = tmp_path_factory.mktemp("inputs")
    rng = np.random.default_rng(0)
    albedo = rng.uniform(0.2, 0.8, (16, 16, 3)).astype(np.float32)
    normal = np.zeros((16, 16, 3), np.float32)
    normal[..., 2] = 1
    noisy = rng.gamma(1.0, 0.5, (16, 16, 3)).astype(np.float32)
    noisy[3, 5, 0], noisy[10, 10, 1], noisy[12, 2, 2] = np.nan, np.inf, -np.inf
    for name, rgb in (("black", np.zeros((16, 16, 3), np.float32)), ("nonfinite", noisy)):
        channels = {f"{layer}{c}": np.ascontiguousarray(a[..., i]) for layer, a, names in
                    (("", rgb, "RGB"), ("albedo.", albedo, "RGB"), ("N.", normal, "XYZ")) for i, c in enumerate(names)}
        with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, channels) as f:
            f.write(str(folder / f"{name}.exr"))
    return folder


@pytest.mark.slow
@pytest.mark.parametrize("name, method", [("black", "ours"), ("nonfinite", "ours"), ("nonfinite", "oidn")])
def test_denoise_outputs_open_in_openimageio_with_real_rgb(inputs, tmp_path, name, method):
    """A denoised image has R, G, B (and its variance and std layers) as stored channels, even when they are
    constant (a black frame's output is all 0), ZIP-compressed; OpenImageIO reads our values."""
    out = tmp_path / f"{name}_{method}.exr"
    proc = cli("denoise", "--exr", inputs / f"{name}.exr", "--out", out, "--spp", "4", "--method", method,
               "--config", TINY)
    theirs = assert_same_channels(out)
    assert oiio_read(out)[1] == "zip"
    ours, record = read_image(out)
    rgb = np.stack([theirs[c] for c in "RGB"], axis=2)
    np.testing.assert_array_equal(rgb, ours["color"])
    np.testing.assert_array_equal(np.stack([theirs[f"variance.{c}"] for c in "RGB"], axis=2), 0)
    assert record["constants"] == {} and np.all(np.isfinite(rgb))
    if name == "black":
        assert np.all(rgb == 0)
    else:
        assert rgb.mean() > 0.1                 # a picture, not a blank: the noisy input's light is kept
        assert "3 non-finite input values replaced by 0" in proc.stdout and record["repaired_nonfinite"] == 3
    if method == "ours":
        assert {"std.R", "std.G", "std.B"} <= set(theirs)
