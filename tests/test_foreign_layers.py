"""EXRs written by other tools: ``denoise --exr`` finds their colour, albedo and normal layers."""
import numpy as np
import OpenEXR
import pytest

from mcdenoise.pipeline.errors import StoreError
from mcdenoise.pipeline.exr import read_layers
from mcdenoise.train import oidn
from tests.helpers import cli


def _write(path, layers: dict[str, np.ndarray]) -> None:
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION},
                      {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in layers.items()}) as f:
        f.write(str(path))


def _layer(prefix: str, image: np.ndarray, suffixes: str) -> dict[str, np.ndarray]:
    return {f"{prefix}.{s}": image[..., i] for i, s in enumerate(suffixes)}


@pytest.mark.slow
def test_mitsubas_aov_exr_gives_colour_albedo_and_its_named_normal(tmp_path):
    """The file Mitsuba's own film writes for `aovs="albedo:albedo,nn:sh_normal"`: the normal is `nn`."""
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba
    mi = import_mitsuba("llvm_ad_rgb")
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=24, height=20, rfilter={"type": "box"})
    d["integrator"] = {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal", "integrator": {"type": "path"}}
    scene = mi.load_dict(d)
    img = np.asarray(mi.render(scene, spp=4), np.float32)
    path = tmp_path / "mitsuba.exr"
    scene.sensors()[0].film().bitmap().write(str(path))
    found: dict = {}
    buffers = read_layers(path, found)
    assert found == {"normal": ("nn.X", "nn.Y", "nn.Z")}
    np.testing.assert_allclose(buffers["color"], img[..., :3], rtol=1e-6)
    np.testing.assert_allclose(buffers["albedo"], img[..., 3:6], rtol=1e-6)
    np.testing.assert_allclose(buffers["normal"], img[..., 6:9], rtol=1e-6)
    assert np.abs(buffers["normal"]).max() > 0.9          # real normals, not the background value

    proc = cli("denoise", "--exr", path, "--out", tmp_path / "out.exr", "--spp", "4", "--method", "oidn")
    assert "normal from 'nn'" in proc.stdout and "rt_hdr_alb_nrm" in proc.stdout
    # OIDN's final-frame mode on the same layers: the aux prefiltered, then its clean-aux network
    proc = cli("denoise", "--exr", path, "--out", tmp_path / "pre.exr", "--method", "oidn_prefilter")
    assert "rt_hdr_calb_cnrm_large" in proc.stdout
    np.testing.assert_array_equal(read_layers(tmp_path / "pre.exr")["color"], oidn.denoise(buffers, clean_aux=True))


def test_blenders_passes_give_the_noisy_image_not_the_denoised_combined(tmp_path):
    rng = np.random.default_rng(0)
    noisy, combined, albedo, normal = (rng.random((6, 5, 3)) for _ in range(4))
    rgba = np.concatenate([combined, np.ones((6, 5, 1))], axis=2)
    path = tmp_path / "blender.exr"
    _write(path, {**_layer("ViewLayer.Combined", rgba, "RGBA"), **_layer("ViewLayer.Noisy Image", noisy, "RGB"),
                  **_layer("ViewLayer.Denoising Albedo", albedo, "RGB"),
                  **_layer("ViewLayer.Denoising Normal", normal, "XYZ"),
                  **_layer("ViewLayer.Denoising Depth", noisy[..., :1], "Z")})
    buffers = read_layers(path)
    np.testing.assert_array_equal(buffers["color"], noisy.astype(np.float32))
    np.testing.assert_array_equal(buffers["albedo"], albedo.astype(np.float32))
    np.testing.assert_array_equal(buffers["normal"], normal.astype(np.float32))

    only_combined = tmp_path / "combined.exr"
    _write(only_combined, _layer("ViewLayer.Combined", rgba, "RGBA"))
    np.testing.assert_array_equal(read_layers(only_combined)["color"], combined.astype(np.float32))


def test_our_names_win_and_ambiguous_or_missing_colour_is_named(tmp_path):
    rng = np.random.default_rng(1)
    a, b = rng.random((4, 4, 3)), rng.random((4, 4, 3))
    ours = tmp_path / "ours.exr"
    _write(ours, {**{c: a[..., i] for i, c in enumerate("RGB")}, **_layer("Combined", b, "RGB")})
    assert np.array_equal(read_layers(ours)["color"], a.astype(np.float32))

    two = tmp_path / "two.exr"
    _write(two, {**_layer("Left.Combined", a, "RGB"), **_layer("Right.Combined", b, "RGB")})
    with pytest.raises(StoreError, match=r"two.exr: layer 'Combined' is in several view layers \(Left, Right\)"):
        read_layers(two)

    none = tmp_path / "none.exr"
    _write(none, _layer("beauty", a, "RGB"))
    with pytest.raises(StoreError, match=r"none.exr: channels R, G, B .* 'Noisy Image' or 'Combined'.*found beauty.B"):
        read_layers(none)
