"""The split-buffer integrator (render/integrator.py) and render_image (render/buffers.py)."""
from __future__ import annotations

import numpy as np
import pytest

from mcdenoise.pipeline.numerics import repair_nonfinite, shorten_normals
from mcdenoise.pipeline.schema import BUFFERS, BY_NAME, OPTIONAL_FEATURES, RADIANCE_COMPONENTS

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def mi():
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba
    return import_mitsuba("llvm_ad_rgb")


def look_at(mi, origin, target, up=(0, 1, 0)):
    return mi.ScalarTransform4f().look_at(origin=list(origin), target=list(target), up=list(up))


def mixed_scene_dict(mi, size=32):
    """Diffuse floor, principled (metallic / spec_trans), roughconductor, dielectric and
    plastic spheres, an area light and a constant environment that the camera sees."""
    from mcdenoise.render.buffers import make_sensor
    T = mi.ScalarTransform4f

    def sphere(c, r, bsdf):
        return {"type": "sphere", "center": c, "radius": r, "bsdf": bsdf}

    return {
        "type": "scene",
        "sensor": make_sensor(mi, look_at(mi, (0, 1.2, 4.0), (0, 0.3, 0)), 45, size, size),
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.35, 0.4]}},
        "light": {"type": "rectangle",
                  "to_world": T().translate([0.5, 2.5, 0.5]).rotate([1, 0, 0], 90).scale(0.6),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [8, 7, 6]}}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.5, 0.4]}}},
        "metal": sphere([-1.0, 0.4, 0], 0.4, {"type": "principled", "metallic": 0.8, "roughness": 0.3,
                                              "base_color": {"type": "rgb", "value": [0.9, 0.6, 0.3]}}),
        "glassy": sphere([0.0, 0.4, 0], 0.4, {"type": "principled", "spec_trans": 0.7, "roughness": 0.2}),
        "rough": sphere([1.0, 0.4, 0], 0.4, {"type": "roughconductor", "alpha": 0.2}),
        "glass": sphere([-0.5, 0.25, 1.0], 0.25, {"type": "dielectric"}),
        "plastic": sphere([0.5, 0.25, 1.0], 0.25, {"type": "plastic"}),
    }


@pytest.fixture(scope="module")
def mixed(mi):
    scene = mi.load_dict(mixed_scene_dict(mi))
    return scene, scene.sensors()[0]


@pytest.fixture(scope="module")
def cbox(mi):
    from mcdenoise.render.buffers import make_sensor
    d = mi.cornell_box()
    d["sensor"] = make_sensor(mi, look_at(mi, (0, 0, 3.9), (0, 0, 0)), 40, 32, 32)
    scene = mi.load_dict(d)
    return scene, scene.sensors()[0]


def frame_mean_and_se(res, name):
    """Frame mean of a buffer and its standard error (box filter: independent pixels)."""
    m, v = res.buffers[name], res.buffers[name + ".variance"]
    n = m.shape[0] * m.shape[1]
    return m.mean(axis=(0, 1)), np.sqrt(v.sum(axis=(0, 1))) / n


# --------------------------------------------------------------------------- radiance split

def test_components_sum_to_color(mi, mixed):
    from mcdenoise.render.buffers import render_image
    scene, sensor = mixed
    res = render_image(mi, scene, sensor, spp=16, seed=3)
    assert set(res.buffers) == {k for b in BUFFERS for k in (b.name, b.name + ".variance")}
    for b in BUFFERS:
        assert res.buffers[b.name].shape == (32, 32, b.size)
        assert res.buffers[b.name].dtype == np.float32
    total = sum(res.buffers[c] for c in RADIANCE_COMPONENTS)
    np.testing.assert_allclose(total, res.buffers["color"], rtol=1e-4, atol=1e-5)
    # Every component is exercised by this scene.
    for c in RADIANCE_COMPONENTS:
        assert res.buffers[c].mean() > 1e-4, c
    assert res.constants == {} and res.nonfinite == {}
    assert res.seconds > 0


def test_diffuse_scene_has_no_specular_components(mi, cbox):
    from mcdenoise.render.buffers import render_image
    scene, sensor = cbox
    res = render_image(mi, scene, sensor, spp=8, seed=1)
    assert np.all(res.buffers["specular_direct"] == 0)
    assert np.all(res.buffers["specular_indirect"] == 0)
    assert res.buffers["diffuse_indirect"].mean() > 0.01


def test_color_matches_builtin_path(mi, mixed):
    """Same estimator as `path` (max_depth 8): frame means agree within a few standard errors."""
    from mcdenoise.render.buffers import render_image
    scene, sensor = mixed
    spp = 512
    res = render_image(mi, scene, sensor, spp=spp, seed=11)
    ref = np.array(mi.render(scene, sensor=sensor, spp=spp, seed=12,
                             integrator=mi.load_dict({"type": "path", "max_depth": 8})))
    mean, se = frame_mean_and_se(res, "color")
    # `path` has the same per-sample variance, so the difference has sqrt(2) se.
    z = (mean - ref[..., :3].mean(axis=(0, 1))) / (np.sqrt(2) * se)
    assert np.all(np.abs(z) < 4.5), z


def test_variance_matches_empirical(mi, cbox):
    """The moment-based variance of the pixel mean agrees with the spread of independent renders."""
    from mcdenoise.render.buffers import render_image
    scene, sensor = cbox
    means, est = {"color": [], "diffuse_indirect": [], "normal": []}, {"color": [], "diffuse_indirect": [], "normal": []}
    for i in range(32):
        res = render_image(mi, scene, sensor, spp=4, seed=1000 + i)
        for k in means:
            means[k].append(res.buffers[k])
            est[k].append(res.buffers[k + ".variance"])
    for k in means:
        empirical = np.var(np.stack(means[k]), axis=0, ddof=1).mean()
        predicted = np.stack(est[k]).mean()
        assert predicted > 0
        assert 0.75 < predicted / empirical < 1.33, (k, predicted, empirical)


# ------------------------------------------------------------------------------- features

def test_disabled_features_leave_other_buffers_identical(mi, mixed):
    from mcdenoise.render.buffers import render_image
    scene, sensor = mixed
    full = render_image(mi, scene, sensor, spp=4, seed=5)
    part = render_image(mi, scene, sensor, spp=4, seed=5, features={"emission"})
    skipped = {"roughness", "metallic", "transmission"}
    for key, arr in full.buffers.items():
        if key.split(".")[0] in skipped:
            assert key not in part.buffers
            assert part.constants[key] == 0.0
        else:
            np.testing.assert_array_equal(part.buffers[key], arr, err_msg=key)
    assert set(part.constants) == {k for f in skipped for k in (f, f + ".variance")}


def test_needed_features(mi, cbox, mixed):
    from mcdenoise.render.buffers import needed_features
    assert needed_features(mi, cbox[0]) == {"emission", "roughness"}
    assert needed_features(mi, mixed[0]) == set(OPTIONAL_FEATURES)
    # A principled material with constant metallic 0 and spec_trans 0 needs neither.
    from mcdenoise.render.buffers import make_sensor
    scene = mi.load_dict({
        "type": "scene", "sensor": make_sensor(mi, look_at(mi, (0, 0, 3), (0, 0, 0)), 40, 8, 8),
        "light": {"type": "point", "position": [0, 0, 3]},
        "s": {"type": "sphere", "bsdf": {"type": "twosided", "bsdf": {"type": "principled"}}},
        "g": {"type": "sphere", "center": [2, 0, 0], "bsdf": {"type": "conductor"}},
    })
    assert needed_features(mi, scene) == {"roughness", "metallic"}


@pytest.mark.parametrize("bsdf, expect", [
    ({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.2, 0.4, 0.6]}},
     dict(roughness=1, metallic=0, transmission=0, albedo=[0.2, 0.4, 0.6])),
    ({"type": "roughconductor", "alpha": 0.09},
     dict(roughness=0.3, metallic=1, transmission=0, albedo=[1, 1, 1])),
    ({"type": "dielectric"}, dict(roughness=0, metallic=0, transmission=1, albedo=[1, 1, 1])),
    ({"type": "roughdielectric", "alpha": 0.25},
     dict(roughness=0.5, metallic=0, transmission=1, albedo=[1, 1, 1])),
    ({"type": "principled", "metallic": 0.7, "roughness": 0.4, "spec_trans": 0.2,
      "base_color": {"type": "rgb", "value": [0.9, 0.5, 0.1]}},
     dict(roughness=0.4, metallic=0.7, transmission=0.2, albedo=[0.9, 0.5, 0.1])),
    ({"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": [0.3, 0.3, 0.3]}},
     dict(roughness=0, metallic=0, transmission=0, albedo=[0.3, 0.3, 0.3])),
])
def test_material_features(mi, bsdf, expect):
    from mcdenoise.render.buffers import make_sensor, render_image
    scene = mi.load_dict({
        "type": "scene", "sensor": make_sensor(mi, look_at(mi, (0, 0, 2), (0, 0, 0)), 30, 4, 4),
        "light": {"type": "point", "position": [0, 0, 2]},
        "plane": {"type": "rectangle", "bsdf": bsdf},
    })
    res = render_image(mi, scene, scene.sensors()[0], spp=1, seed=0)
    for name, value in expect.items():
        np.testing.assert_allclose(res.buffers[name], np.broadcast_to(value, res.buffers[name].shape),
                                   atol=1e-5, err_msg=name)


# ------------------------------------------------------------------ geometry and background

def test_depth_normal_background(mi):
    """A plane 2.5 in front of a wide-angle camera covers the left half of the image; the
    right half sees the environment."""
    from mcdenoise.render.buffers import make_sensor, render_image
    T = mi.ScalarTransform4f
    d = 2.5
    scene = mi.load_dict({
        "type": "scene",
        "sensor": make_sensor(mi, look_at(mi, (0, 0, d), (0, 0, 0)), 70, 32, 32),
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}},
        # Rectangle spanning x in [-20, 0]: its edge lies on the view axis, a pixel border.
        "plane": {"type": "rectangle", "to_world": T().translate([-10, 0, 0]).scale([10, 20, 1]),
                  "bsdf": {"type": "diffuse"}},
    })
    res = render_image(mi, scene, scene.sensors()[0], spp=4, seed=2)
    b = res.buffers
    depth = b["depth"][..., 0]
    hit = depth > 0
    assert hit.sum() == 32 * 16  # exactly one half, no mixed pixels
    # Camera-space z is constant on a plane facing the camera (ray length is not: up to ~1.5 d).
    np.testing.assert_allclose(depth[hit], d, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(b["normal"][hit], axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(b["normal"][hit], np.broadcast_to([0, 0, 1], (hit.sum(), 3)), atol=1e-5)
    bg = ~hit
    for buf in BUFFERS:
        vals = b[buf.name][bg]
        if buf.name in ("color", "emission"):
            np.testing.assert_allclose(vals, 0.5, rtol=1e-6)
        else:
            assert np.all(vals == buf.background), buf.name
        assert np.all(b[buf.name + ".variance"][bg] == 0), buf.name
    # On the plane nothing is emitted and only the environment lights it (diffuse).
    assert np.all(b["emission"][hit] == 0)
    assert b["diffuse_direct"][hit].mean() > 0.1


def test_normals_unit_length_on_curved_hits(mi, mixed):
    from mcdenoise.render.buffers import render_image
    scene, sensor = mixed
    res = render_image(mi, scene, sensor, spp=1, seed=9)  # one sample per pixel: no averaging
    hit = res.buffers["depth"][..., 0] > 0
    assert 0 < hit.sum() < hit.size
    np.testing.assert_allclose(np.linalg.norm(res.buffers["normal"][hit], axis=-1), 1.0, atol=1e-4)
    assert np.all(res.buffers["normal"][~hit] == 0)
    for name in ("albedo", "roughness", "metallic", "transmission"):
        v = res.buffers[name]
        assert v.min() >= 0 and v.max() <= 1 + 1e-6, name


# ----------------------------------------------------------------------------- numerics

def test_repair_nonfinite_counts():
    a = np.array([[1.0, np.nan], [np.inf, -np.inf]], dtype=np.float32)
    b = np.ones((2, 2), dtype=np.float32)
    counts = repair_nonfinite({"a": a, "b": b})
    assert counts == {"a": 3}
    assert np.all(a == np.array([[1, 0], [0, 0]]))


def test_integrator_props_and_registration(mi):
    from mcdenoise.render.integrator import register
    register(mi)
    register(mi)  # idempotent
    integ = mi.load_dict({"type": "split", "features": "metallic", "moments": False, "max_depth": 3})
    names = integ.aov_names()
    assert "metallic.Y" in names and "roughness.Y" not in names and "emission.R" not in names
    assert not any(".m2." in n for n in names)
    assert "Z" not in names
    with pytest.raises(Exception):
        mi.load_dict({"type": "split", "features": "sheen"})
    assert BY_NAME["depth"].size == 1


def test_shorten_normals_rescales_only_overlong_normals_and_counts_them():
    """Unit normals (and 0 where nothing was hit) are left bit for bit; a 1e3-long one becomes unit length."""
    rng = np.random.default_rng(0)
    n = rng.normal(size=(8, 8, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[0, 0] = 0.0
    n[1, :3] *= 1000.0
    before = n.copy()
    assert shorten_normals(n) == 3
    assert np.array_equal(n[2:], before[2:]) and np.array_equal(n[0], before[0])
    np.testing.assert_allclose(np.linalg.norm(n[1, :3], axis=-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(n[1, :3], before[1, :3] / np.linalg.norm(before[1, :3], axis=-1, keepdims=True), rtol=1e-6)
    assert shorten_normals(n) == 0
