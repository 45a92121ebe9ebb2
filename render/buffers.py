"""Render every schema buffer of one image in one pass with the ``split`` integrator.

``render_image`` returns per-buffer means and variances of the pixel mean (from the per-sample
second moments the integrator emits), constants for the optional features that were not
computed, and the non-finite repair counts. ``needed_features`` decides which optional
features a scene can produce at all; ``make_sensor`` builds the box-filtered camera every
buffer must use.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mcdenoise.pipeline.motion import FAR_CLIP, NEAR_CLIP
from mcdenoise.pipeline.numerics import repair_nonfinite, sample_variance_of_mean
from mcdenoise.pipeline.schema import BY_NAME, OPTIONAL_FEATURES, variance_name
from mcdenoise.render.integrator import aov_layout, output_buffers, parse_features, register

# Value an optional feature takes where it is not computed (the integrator would produce it
# for a scene that cannot exhibit the feature, and for background pixels).
NOT_COMPUTED_VALUE = 0.0


@dataclass
class RenderResult:
    buffers: dict[str, np.ndarray]                  # name / name.variance -> HxWxC float32
    constants: dict[str, float] = field(default_factory=dict)  # skipped buffers (+ variances)
    nonfinite: dict[str, int] = field(default_factory=dict)    # key -> values repaired to 0
    seconds: float = 0.0                            # render + develop wall time


_INTEGRATORS: dict[tuple, object] = {}


def get_integrator(mi, features=None, max_depth: int = 8, rr_depth: int = 5, moments: bool = True):
    """A cached ``split`` integrator: reusing the instance keeps drjit's kernel cache hot."""
    feats = parse_features(features)
    key = (mi.variant(), feats, int(max_depth), int(rr_depth), bool(moments))
    integ = _INTEGRATORS.get(key)
    if integ is None:
        register(mi)
        integ = mi.load_dict({"type": "split", "features": ",".join(feats) or "",
                              "max_depth": int(max_depth), "rr_depth": int(rr_depth),
                              "moments": bool(moments)})
        _INTEGRATORS[key] = integ
    return integ


def make_sensor(mi, to_world, fov: float, width: int, height: int,
                near_clip: float = NEAR_CLIP, far_clip: float = FAR_CLIP):
    """Perspective camera (``fov`` in degrees along x) with a box-filtered RGB ``hdrfilm``.

    The box filter keeps each sample in its own pixel, so pixel noise is independent and the
    moment-based variances are right.
    """
    return mi.load_dict({
        "type": "perspective",
        "to_world": to_world,
        "fov": float(fov),
        "near_clip": float(near_clip),
        "far_clip": float(far_clip),
        "film": {
            "type": "hdrfilm",
            "width": int(width),
            "height": int(height),
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
            "sample_border": False,
        },
    })


def render_image(mi, scene, sensor, spp: int, seed: int, features: set[str] | None = None,
                 max_depth: int = 8, rr_depth: int = 5) -> RenderResult:
    """Render all buffers (``features`` = the optional ones to compute; None = all)."""
    if spp < 1:
        raise ValueError("spp must be >= 1")
    integ = get_integrator(mi, features, max_depth, rr_depth, moments=True)
    names = output_buffers(integ.features)
    layout = aov_layout(integ.features, True)

    t0 = time.perf_counter()
    img = mi.render(scene, sensor=sensor, spp=int(spp), seed=int(seed), integrator=integ)
    arr = np.array(img, dtype=np.float32)
    seconds = time.perf_counter() - t0

    n_aov = sum(size for _, _, size in layout)
    base = arr.shape[2] - n_aov
    if base not in (3, 4):  # R,G,B or R,G,B,A, then the AOVs in aov_names() order
        raise RuntimeError(f"unexpected film channel count {arr.shape[2]} for {n_aov} AOVs")
    first: dict[str, np.ndarray] = {"color": arr[..., 0:3]}
    second: dict[str, np.ndarray] = {}
    c = base
    for name, m2, size in layout:
        (second if m2 else first)[name] = arr[..., c:c + size]
        c += size

    buffers: dict[str, np.ndarray] = {}
    for name in names:
        m1 = np.ascontiguousarray(first[name], dtype=np.float32)
        buffers[name] = m1
        buffers[variance_name(name)] = sample_variance_of_mean(m1, second[name], int(spp))
    nonfinite = repair_nonfinite(buffers)

    constants: dict[str, float] = {}
    for feat in OPTIONAL_FEATURES:
        if feat not in names:
            constants[feat] = NOT_COMPUTED_VALUE
            constants[variance_name(feat)] = 0.0
    for name in names:
        assert buffers[name].shape[-1] == BY_NAME[name].size
    return RenderResult(buffers=buffers, constants=constants, nonfinite=nonfinite, seconds=seconds)


# ---------------------------------------------------------------------------- scene analysis

def _bool(x) -> bool:
    try:
        return bool(x)
    except (TypeError, ValueError):
        return bool(np.any(np.asarray(x)))


def _constant_param(mi, obj, name: str) -> float | None:
    """The value of ``obj``'s parameter ``name`` if it is a constant everywhere, else None."""
    try:
        params = mi.traverse(obj)
    except Exception:  # noqa: BLE001 - anything unusual counts as "not known constant"
        return None
    values = []
    for key in params.keys():
        parts = key.split(".")
        if name not in parts:
            continue
        if parts[-1] != "value" or parts[-2] != name:
            return None  # a texture (bitmap data, ...): varies
        values.append(np.asarray(params[key], dtype=np.float64).reshape(-1))
    if not values:
        return None
    flat = np.concatenate(values)
    return float(flat[0]) if np.all(flat == flat[0]) else None


def needed_features(mi, scene) -> set[str]:
    """The optional features the scene's emitters and BSDFs can make non-zero.

    Mirrors the integrator's rules on the top-level BSDF of each shape (the integrator
    sees wrappers such as ``twosided`` only through their flags and forwarded attributes,
    so the same test here is exact for them):

    * emission: any area emitter or visible infinite emitter (envmap, constant); point,
      spot and directional lights cannot be seen by the camera.
    * metallic: a reflection-only BSDF without diffuse lobe (conductors), or a 'metallic'
      attribute (principled) that is not the constant 0.
    * transmission: a BSDF with glossy/delta transmission and no diffuse lobe (dielectrics),
      or a 'spec_trans' attribute that is not the constant 0.
    * roughness: any glossy lobe, or a diffuse BSDF without delta lobes (roughness 1); only
      scenes made purely of smooth (delta) materials skip it.
    Shapes whose BSDF cannot be inspected (instances, shape groups) enable everything.
    """
    F = mi.BSDFFlags
    need: set[str] = set()
    for em in scene.emitters():
        fl = em.flags()
        if mi.has_flag(fl, mi.EmitterFlags.Surface) or (
                mi.has_flag(fl, mi.EmitterFlags.Infinite)
                and not mi.has_flag(fl, mi.EmitterFlags.DeltaDirection)):
            need.add("emission")
    env = scene.environment() if hasattr(scene, "environment") else None
    if env is not None:
        need.add("emission")

    for shape in scene.shapes():
        bsdf = shape.bsdf() if hasattr(shape, "bsdf") else None
        is_instance = shape.is_instance() if hasattr(shape, "is_instance") else False
        if bsdf is None or is_instance:
            return set(OPTIONAL_FEATURES)
        if shape.is_emitter():
            need.add("emission")
        fl = int(bsdf.flags())
        diffuse = mi.has_flag(fl, F.Diffuse)
        glossy = mi.has_flag(fl, F.Glossy)
        delta = mi.has_flag(fl, F.Delta)
        spec_trans = mi.has_flag(fl, F.GlossyTransmission) or mi.has_flag(fl, F.DeltaTransmission)
        any_trans = mi.has_flag(fl, F.Transmission)
        reflect = mi.has_flag(fl, F.Reflection)

        if glossy or (diffuse and not delta):
            need.add("roughness")
        if reflect and not diffuse and not any_trans:
            need.add("metallic")
        if spec_trans and not diffuse:
            need.add("transmission")
        for attr, feat in (("metallic", "metallic"), ("spec_trans", "transmission")):
            if feat in need or not _bool(bsdf.has_attribute(attr)):
                continue
            if _constant_param(mi, bsdf, attr) != 0.0:
                need.add(feat)
    return need
