"""EXRs written by other tools: ``denoise --exr`` finds their colour, albedo and normal layers."""
import numpy as np
import OpenEXR
import pytest

from mcdenoise.pipeline.errors import StoreError
from mcdenoise.pipeline.exr import CYCLES_EXCESS, CYCLES_LOBES, read_layers
from mcdenoise.pipeline.schema import RADIANCE_COMPONENTS, beauty_from_components
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


def _cycles_light(rng, shape, spelling: int, transmission: bool = True):
    """Cycles' light passes of a made-up frame (``CYCLES_LOBES``, old or new spelling): each lobe's light and colour,
    the emitters and the world, and the noisy beauty they add up to (Blender's manual's formula)."""
    lobes = [lobe for lobe in CYCLES_LOBES if transmission or lobe != "transmission"]
    light = {lobe: (rng.random(shape), rng.random(shape), rng.random(shape)) for lobe in lobes}
    emit, world = rng.random(shape) * (rng.random(shape[:2]) < 0.2)[..., None], rng.random(shape) * 0.1
    layers = {}
    for lobe in lobes:
        for names, image in zip(CYCLES_LOBES[lobe], light[lobe]):
            layers.update(_layer(f"ViewLayer.{names[spelling]}", image, "RGB"))
    beauty = sum((d + i) * c for d, i, c in light.values()) + emit + world
    layers.update({**_layer("ViewLayer.Emit", emit, "RGB"), **_layer("ViewLayer.Env", world, "RGB"),
                   **_layer("ViewLayer.Noisy Image", beauty, "RGB")})
    return layers, light, emit + world, beauty


@pytest.mark.parametrize("spelling", [0, 1])
def test_cycles_light_passes_give_the_components_that_add_up_to_the_beauty(tmp_path, spelling):
    """The diffuse lobe's light times its colour is the diffuse light; glossy and transmission make the reflections;
    emission is the rest (the emitters and the world); the five add up to the noisy beauty (float32 rounding of each
    product, a few ulp of values below 4)."""
    rng = np.random.default_rng(5 + spelling)
    layers, light, rest, beauty = _cycles_light(rng, (6, 5, 3), spelling)
    path = tmp_path / "cycles.exr"
    _write(path, layers)
    found: dict = {}
    buffers = read_layers(path, found)
    f32 = lambda x: x.astype(np.float32).astype(np.float64)     # noqa: E731  (what the file holds)
    lit = {lobe: tuple(map(f32, images)) for lobe, images in light.items()}
    expected = {"diffuse_direct": lit["diffuse"][0] * lit["diffuse"][2],
                "diffuse_indirect": lit["diffuse"][1] * lit["diffuse"][2],
                "specular_direct": lit["glossy"][0] * lit["glossy"][2] + lit["transmission"][0] * lit["transmission"][2],
                "specular_indirect": lit["glossy"][1] * lit["glossy"][2] + lit["transmission"][1] * lit["transmission"][2]}
    for name, value in expected.items():
        np.testing.assert_allclose(buffers[name], value, rtol=1e-6)
    np.testing.assert_allclose(buffers["emission"], rest, atol=1e-6)
    np.testing.assert_allclose(beauty_from_components(buffers), buffers["color"], atol=1e-6)
    direct, _, colour = CYCLES_LOBES["diffuse"]
    assert found["diffuse_direct"] == tuple(f"ViewLayer.{n[spelling]}.{c}" for n in (direct, colour) for c in "RGB")


def test_cycles_light_passes_need_diffuse_and_glossy_and_must_not_exceed_the_beauty(tmp_path):
    rng = np.random.default_rng(9)
    layers, light, rest, beauty = _cycles_light(rng, (4, 6, 3), 0, transmission=False)
    path = tmp_path / "cycles.exr"
    _write(path, layers)
    buffers = read_layers(path)                 # no transmission passes: the glossy lobe alone makes the reflections
    d, i, c = (x.astype(np.float32) for x in light["glossy"])
    np.testing.assert_allclose(buffers["specular_indirect"], i.astype(np.float64) * c, rtol=1e-6)
    np.testing.assert_allclose(beauty_from_components(buffers), buffers["color"], atol=1e-6)
    no_glossy = tmp_path / "no_glossy.exr"
    _write(no_glossy, {k: v for k, v in layers.items() if "Gloss" not in k})
    assert not set(RADIANCE_COMPONENTS) & set(read_layers(no_glossy))
    # a beauty that is not the passes' sum (Blender's denoised Combined, no Noisy Image): passes left out
    smooth = tmp_path / "denoised.exr"
    noisy = {k: v for k, v in layers.items() if "Noisy Image" not in k}
    _write(smooth, {**noisy, **_layer("ViewLayer.Combined", 0.9 * beauty, "RGB")})
    assert not set(RADIANCE_COMPONENTS) & set(read_layers(smooth))
    _write(smooth, {**noisy, **_layer("ViewLayer.Combined", beauty * (1 - 0.5 * CYCLES_EXCESS), "RGB")})
    assert set(RADIANCE_COMPONENTS) <= set(read_layers(smooth))      # within the rounding allowance: read


def test_the_sample_count_of_a_cycles_render_is_read_from_its_header(tmp_path):
    """Cycles stamps ``cycles.<view layer>.samples``; ``denoise`` reads it where the file has no record of ours."""
    from mcdenoise.train.infer import DEFAULT_EXR_SPP, exr_spp
    image = {c: np.full((4, 4), 0.5, np.float32) for c in "RGB"}

    def stamped(name, **stamps):
        path = tmp_path / name
        with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, **stamps}, image) as f:
            f.write(str(path))
        return path
    assert exr_spp(stamped("cycles.exr", **{"cycles.ViewLayer.samples": "4"})) == (4, "from Cycles' header")
    two = {"cycles.A.samples": "4", "cycles.B.samples": "64"}            # view layers that disagree: not guessed
    for path in (stamped("two.exr", **two), stamped("bad.exr", **{"cycles.ViewLayer.samples": "4x"}),
                 stamped("zero.exr", **{"cycles.ViewLayer.samples": "0"}), stamped("none.exr")):
        assert exr_spp(path) == (DEFAULT_EXR_SPP, "not recorded in the file: assumed"), path
