r"""The split-buffer path tracer (``split``): one pass, every buffer of ``pipeline.schema``.

Importable before a Mitsuba variant is set: the integrator class is built on first use by
:func:`integrator_class` (after ``import_mitsuba``) and registered by :func:`register`.

Estimator
---------
A unidirectional path tracer with next-event estimation (NEE) and power-heuristic MIS, the
same estimator as Mitsuba's C++ ``path`` (same ``max_depth``/``rr_depth`` convention, same
Russian roulette), so its ``color`` equals ``path``'s in expectation. Writing a path's vertices
x_0 (camera), x_1 (first hit), x_2, ... and the contribution collected at vertex x_k as

    L_k = beta_k * [ w_bsdf * Le(x_k)            (emitter hit by the BSDF sample of x_{k-1})
                   + w_nee  * f(x_k) Le / p_nee ] (emitter sampled from x_k),

one sample of the pixel is ``color = sum_k L_k`` and is split *exactly* into

    emission          = Le(x_1)                      (k = 1, the camera sees an emitter/envmap)
    diffuse_direct    = NEE at x_1 via the diffuse lobe + BSDF-hit term at x_2 if s_1 = diffuse
    specular_direct   = NEE at x_1 via the other lobes  + BSDF-hit term at x_2 if s_1 != diffuse
    diffuse_indirect  = everything later (NEE at x_k, k>=2; BSDF hits at x_k, k>=3), s_1 = diffuse
    specular_indirect = the same when s_1 != diffuse

where s_1 is ``bs.sampled_type`` of the BSDF sample drawn at x_1. ``color`` is returned as the
sum of the five components, so they add up to it per sample up to float round-off.

Exact and approximate parts of the diffuse/specular split
---------------------------------------------------------
* BSDF-sampled continuation: exact attribution by ``sampled_type`` (an unbiased split of the
  estimator; every BSDF reports which lobe it sampled).
* NEE at x_1: the diffuse part is ``f_d`` evaluated with a ``BSDFContext`` whose ``type_mask``
  is the diffuse lobes, specular = total - diffuse. Exact for BSDFs that honour the mask
  (diffuse, plastic, roughplastic, conductors, dielectrics, blendbsdf, twosided of those).
* ``principled`` ignores ``type_mask``. Such lanes are detected *per sample*: an evaluation
  with an empty mask returns non-zero only for a BSDF that ignores the mask. There the diffuse
  part is approximated by a Lambertian lobe (1 - metallic)(1 - spec_trans) base_color cos/pi
  (the attributes ``principled`` exposes), clipped to [0, f]; the Disney retro-reflection and
  sheen terms therefore land in ``specular_direct``. The sum stays exact.
* In expectation, the direct split is thus a blend of two definitions: the NEE strategy
  splits by f_d / f, the BSDF strategy by the lobe-selection probability of the sample
  (both unbiased splits of the total; they coincide when lobe selection is proportional to
  the lobe's value). The indirect split is by sampled lobe, as the schema defines it.
* If ``emission`` is not among the computed features, directly seen emission still counts
  in ``color`` but is not output; ``render.buffers.needed_features`` only drops it for
  scenes without visible emitters, where it is 0.

Auxiliary features at the first hit (0 where the camera ray escapes)
---------------------------------------------------------------------
* albedo: ``eval_diffuse_reflectance`` where the BSDF has a diffuse lobe, 1 for purely
  specular BSDFs (OIDN convention), 0 on area emitters. ``principled`` reports its
  ``base_color`` (also for metals, which is what a denoiser wants as the albedo).
* normal: world-space shading normal; depth: camera-space z, dot(p - o, forward) of the
  sensor that is being rendered (set in :meth:`render`).
* roughness: principled 'roughness'; glossy lobes sqrt(alpha) (sqrt(sqrt(alpha_u alpha_v))
  if anisotropic); smooth (delta-only specular) 0; purely diffuse 1.
* metallic: principled 'metallic'; 1 for reflection-only BSDFs without diffuse lobe.
* transmission: principled 'spec_trans'; 1 for BSDFs with glossy/delta transmission and no
  diffuse lobe (dielectrics, thindielectric, roughdielectric).

Optional features (``features`` property) that are not listed are not traced at all. With
``moments`` every channel's per-sample square is emitted as an extra AOV, so the film gives
E[x] and E[x^2] (hence the variance of the pixel mean) in one pass.
"""
from __future__ import annotations

from mcdenoise.pipeline.schema import BUFFERS, OPTIONAL_FEATURES

# Buffers the integrator always computes (the optional ones are added when enabled).
ALWAYS = tuple(b.name for b in BUFFERS if b.name not in OPTIONAL_FEATURES)

_CLASS = {}

# Set by integrator_class(): @dr.syntax re-compiles `sample` against the module globals, so
# the modules and helpers it uses must live here rather than in a closure.
mi = None
dr = None


def mis_weight(pdf_a, pdf_b):
    """Power heuristic; 0 where both densities vanish (or overflow)."""
    a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0)


def parse_features(value) -> tuple[str, ...]:
    """Normalise a features spec (comma string, iterable, None = all) to schema order."""
    if value is None:
        return OPTIONAL_FEATURES
    if isinstance(value, str):
        value = [v.strip() for v in value.split(",") if v.strip()]
    value = set(value)
    unknown = value - set(OPTIONAL_FEATURES)
    if unknown:
        raise ValueError(f"unknown features {sorted(unknown)}; known: {OPTIONAL_FEATURES}")
    return tuple(f for f in OPTIONAL_FEATURES if f in value)


def output_buffers(features) -> tuple[str, ...]:
    """Buffer names produced for ``features``, in schema order (``color`` first)."""
    feats = set(parse_features(features))
    return tuple(b.name for b in BUFFERS if b.name in ALWAYS or b.name in feats)


def aov_layout(features, moments: bool) -> list[tuple[str, bool, int]]:
    """Film channel layout after R,G,B: (buffer, is_second_moment, n_channels) per block."""
    from mcdenoise.pipeline.schema import BY_NAME
    names = output_buffers(features)
    layout = [(n, False, BY_NAME[n].size) for n in names if n != "color"]
    if moments:
        layout += [(n, True, BY_NAME[n].size) for n in names]
    return layout


def aov_channel_names(layout: list[tuple[str, bool, int]]) -> list[str]:
    """Film AOV channel names of ``aov_layout``'s blocks: ``<buffer>.<c>``, ``<buffer>.m2.<c>`` for second moments."""
    from mcdenoise.pipeline.schema import BY_NAME
    names = []
    for name, m2, _ in layout:
        b = BY_NAME[name]
        chans = b.channels
        names += [f"{name}.m2.{c}" if m2 else f"{name}.{c}" for c in chans]
    return names


# First-hit features (see the module docstring); ``hit``: the lanes whose camera ray hit, the
# ``has_*`` masks: the BSDF's lobe flags. Absent attributes evaluate to 0.

def _roughness(bsdf, si, hit, has_glossy, has_delta, has_diffuse):
    """principled 'roughness' or sqrt(alpha) of glossy lobes; 0 for delta-only, 1 for purely diffuse."""
    alpha = bsdf.eval_attribute_1("alpha", si, hit & has_glossy)
    alpha += dr.sqrt(bsdf.eval_attribute_1("alpha_u", si, hit & has_glossy)
                     * bsdf.eval_attribute_1("alpha_v", si, hit & has_glossy))
    r_p = bsdf.eval_attribute_1("roughness", si, hit & has_glossy)
    rough = dr.select(has_glossy, dr.maximum(r_p, dr.sqrt(alpha)),
                      dr.select(has_delta, 0, dr.select(has_diffuse, 1, 0)))
    return dr.select(hit, dr.clip(rough, 0, 1), 0)


def _metallic(bsdf, si, hit, flags, has_diffuse):
    """principled 'metallic'; 1 for reflection-only BSDFs without a diffuse lobe."""
    conductor = (mi.has_flag(flags, mi.BSDFFlags.Reflection) & ~has_diffuse
                 & ~mi.has_flag(flags, mi.BSDFFlags.Transmission))
    metal = dr.maximum(bsdf.eval_attribute_1("metallic", si, hit & has_diffuse),
                       dr.select(conductor, 1, 0))
    return dr.select(hit, metal, 0)


def _transmission(bsdf, si, hit, has_trans, has_diffuse):
    """principled 'spec_trans'; 1 for BSDFs with glossy/delta transmission and no diffuse lobe."""
    st = bsdf.eval_attribute_1("spec_trans", si, hit & has_diffuse)
    trans = dr.select(has_trans & ~has_diffuse, 1, st)
    return dr.select(hit, trans, 0)


def integrator_class(mitsuba):
    """Build (once per variant) the ``SplitIntegrator`` class; needs a variant set."""
    global mi, dr
    variant = mitsuba.variant()
    if variant is None:
        raise RuntimeError("set a Mitsuba variant first (pipeline.mitsuba_env.import_mitsuba)")
    if variant in _CLASS:
        return _CLASS[variant]
    import drjit
    mi, dr = mitsuba, drjit

    class SplitIntegrator(mi.SamplingIntegrator):
        __doc__ = __doc__

        def __init__(self, props=None):
            props = mi.Properties() if props is None else props
            super().__init__(props)
            max_depth = props.get("max_depth", 8)
            if max_depth < 0 and max_depth != -1:
                raise ValueError("'max_depth' must be -1 (infinite) or >= 0")
            # Mitsuba convention: -1 = unbounded.
            self.max_depth = int(max_depth) if max_depth != -1 else 0xFFFFFFFF
            self.rr_depth = int(props.get("rr_depth", 5))
            if self.rr_depth <= 0:
                raise ValueError("'rr_depth' must be > 0")
            self.features = parse_features(props.get("features", ",".join(OPTIONAL_FEATURES)))
            self.moments = bool(props.get("moments", True))
            self.buffers = output_buffers(self.features)
            self.layout = aov_layout(self.features, self.moments)
            # Camera origin / forward axis for camera-space depth; opaque so that a new
            # camera does not change the kernel (the kernel cache stays hot).
            self.set_camera(None)

        # ------------------------------------------------------------------ setup

        def set_camera(self, sensor):
            """Use ``sensor``'s origin and view axis (+z of its to_world) for ``depth``."""
            if sensor is None:
                o, f = mi.Point3f(0, 0, 0), mi.Vector3f(0, 0, 1)
            else:
                T = sensor.world_transform()
                o = T @ mi.Point3f(0, 0, 0)
                f = dr.normalize(T @ mi.Vector3f(0, 0, 1))
            self.cam_o = mi.Point3f(o)
            self.cam_f = mi.Vector3f(f)
            dr.make_opaque(self.cam_o, self.cam_f)

        def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
            if isinstance(sensor, int):
                sensor = scene.sensors()[sensor]
            self.set_camera(sensor)
            return mi.SamplingIntegrator.render(self, scene, sensor, seed, spp, develop, evaluate)

        def aov_names(self):
            return aov_channel_names(self.layout)

        def to_string(self):
            return (f"SplitIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                    f"features={','.join(self.features)}, moments={self.moments}]")

        # ------------------------------------------------------------- features

        def first_hit_features(self, scene, si, bsdf, active):
            """Auxiliary buffers at the first hit; 0 where the camera ray escaped."""
            hit = active & si.is_valid()
            out = {}
            flags = bsdf.flags()
            has_diffuse = mi.has_flag(flags, mi.BSDFFlags.Diffuse)
            has_glossy = mi.has_flag(flags, mi.BSDFFlags.Glossy)
            has_delta = mi.has_flag(flags, mi.BSDFFlags.Delta)
            has_trans = (mi.has_flag(flags, mi.BSDFFlags.GlossyTransmission)
                         | mi.has_flag(flags, mi.BSDFFlags.DeltaTransmission))

            # Albedo: diffuse reflectance (the default eval_diffuse_reflectance of a
            # non-diffuse BSDF is meaningless, hence the flag test); 1 for purely specular.
            on_emitter = si.emitter(scene) != None  # noqa: E711 (drjit pointer compare)
            rho = bsdf.eval_diffuse_reflectance(si, hit & has_diffuse)
            albedo = dr.select(has_diffuse, mi.Color3f(rho), mi.Color3f(1))
            out["albedo"] = dr.select(hit & ~on_emitter, albedo, mi.Color3f(0))
            out["normal"] = dr.select(hit, si.sh_frame.n, mi.Vector3f(0))
            out["depth"] = dr.select(hit, dr.dot(si.p - self.cam_o, self.cam_f), 0)

            # Attributes absent from a BSDF evaluate to 0, which lets one expression serve
            # every lane: principled exposes roughness/metallic/spec_trans, the microfacet
            # BSDFs alpha (or alpha_u/alpha_v), and the flags classify the rest.
            if "roughness" in self.features:
                out["roughness"] = _roughness(bsdf, si, hit, has_glossy, has_delta, has_diffuse)
            if "metallic" in self.features:
                out["metallic"] = _metallic(bsdf, si, hit, flags, has_diffuse)
            if "transmission" in self.features:
                out["transmission"] = _transmission(bsdf, si, hit, has_trans, has_diffuse)
            return out

        # ---------------------------------------------------------------- sample

        @dr.syntax
        def sample(self, scene, sampler, ray, medium=None, active=True):
            ctx = mi.BSDFContext()
            active = mi.Bool(active)
            ray_d = ray

            # First hit outside the loop: it feeds the auxiliary buffers and the emission
            # buffer; the loop continues from it.
            si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True, active=active)
            bsdf0 = si.bsdf(ray_d)  # with ray differentials for texture filtering
            aux = self.first_hit_features(scene, si, bsdf0, active)
            valid = active & si.is_valid()

            # Emitter (or environment) seen directly: beta = 1, MIS weight 1 (max_depth 0
            # renders nothing, as in `path`).
            L_em = mi.Spectrum(si.emitter(scene).eval(si, active & (self.max_depth > 0)))

            ray = mi.Ray3f(ray)
            depth = mi.UInt32(0)
            beta = mi.Spectrum(1)
            eta = mi.Float(1)
            L_nee0 = mi.Spectrum(0)       # NEE at the first hit (all lobes)
            L_nee0_d = mi.Spectrum(0)     # ... its diffuse part
            L_hit1 = mi.Spectrum(0)       # emitter hit by the first BSDF sample
            L_ind = mi.Spectrum(0)        # everything later
            first_diffuse = mi.Bool(False)
            prev_si = mi.Interaction3f(si)
            prev_pdf = mi.Float(1)
            prev_delta = mi.Bool(True)

            while dr.hint(active, label="split path tracer"):
                first = depth == 0
                bsdf = si.bsdf()

                # Emitter hit by the previous BSDF sample (depth 0 is L_em, done above).
                hit_em = active & ~first
                ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
                em_pdf = scene.pdf_emitter_direction(prev_si, ds, hit_em & ~prev_delta)
                w_bsdf = dr.select(prev_delta, 1, mis_weight(prev_pdf, em_pdf))
                Le = beta * w_bsdf * ds.emitter.eval(si, hit_em & (prev_pdf > 0))

                active_next = active & (depth + 1 < self.max_depth) & si.is_valid()

                # Next-event estimation (same sample order as the C++ path tracer).
                active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
                active_em &= ds.pdf != 0
                wo = si.to_local(ds.d)
                bsdf_val, bsdf_pdf, bs, bsdf_weight = bsdf.eval_pdf_sample(
                    ctx, si, wo, sampler.next_1d(), sampler.next_2d(), active_next)
                w_nee = dr.select(ds.delta, 1, mis_weight(ds.pdf, bsdf_pdf))
                Lr = dr.select(active_em, beta * bsdf_val * em_weight * w_nee, 0)

                # Lobe split of the first-hit NEE term (see the docstring).
                split = active_em & first
                f_d = self.diffuse_bsdf(bsdf, si, wo, bsdf_val, split)
                Lr_d = dr.select(split, beta * f_d * em_weight * w_nee, 0)

                # Route this vertex's contributions.
                if first:
                    L_nee0 += Lr
                    L_nee0_d += Lr_d
                    first_diffuse = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Diffuse)
                elif depth == 1:
                    L_hit1 += Le
                    L_ind += Lr
                else:
                    L_ind += Le + Lr

                # Continue the path.
                ray = si.spawn_ray(si.to_world(bs.wo))
                beta *= bsdf_weight
                eta *= bs.eta
                prev_si = mi.Interaction3f(si)
                prev_pdf = bs.pdf
                prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                depth[si.is_valid()] += 1

                # Russian roulette (as in Mitsuba's path: cancel eta^2, at most 0.95).
                beta_max = dr.max(beta)
                rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
                rr_active = depth >= self.rr_depth
                rr_continue = sampler.next_1d() < rr_prob
                beta[rr_active] *= dr.rcp(rr_prob)
                active = active_next & (~rr_active | rr_continue) & (beta_max != 0)

                si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=False,
                                         active=active)

            parts = {
                "emission": L_em,
                "diffuse_direct": L_nee0_d + dr.select(first_diffuse, L_hit1, 0),
                "specular_direct": (L_nee0 - L_nee0_d) + dr.select(first_diffuse, 0, L_hit1),
                "diffuse_indirect": dr.select(first_diffuse, L_ind, 0),
                "specular_indirect": dr.select(first_diffuse, 0, L_ind),
            }
            color = (parts["emission"] + parts["diffuse_direct"] + parts["specular_direct"]
                     + parts["diffuse_indirect"] + parts["specular_indirect"])
            return color, valid, self.aov_values(dict(parts, color=color, **aux))

        @dr.syntax   # the `if` on a mask becomes dr.if_stmt
        def diffuse_bsdf(self, bsdf, si, wo, bsdf_val, active):
            """The diffuse lobe of the BSDF value ``bsdf_val`` towards ``wo`` (the NEE split at the first hit).

            A diffuse-only context answers it, except for BSDFs that ignore the context's lobe mask
            (principled: an empty context still returns a value); for those the diffuse lobe is the
            Lambertian base_color·(1 − metallic)·(1 − spec_trans)·cos/π, clipped to the full value."""
            ctx_diffuse = mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.Diffuse)
            ctx_none = mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.Empty)
            f_d = bsdf.eval(ctx_diffuse, si, wo, active)
            ignores_mask = active & dr.any(bsdf.eval(ctx_none, si, wo, active) != 0)
            if ignores_mask:
                base = bsdf.eval_attribute_3("base_color", si, ignores_mask)
                kd = ((1 - bsdf.eval_attribute_1("metallic", si, ignores_mask))
                      * (1 - bsdf.eval_attribute_1("spec_trans", si, ignores_mask)))
                cos_o = dr.maximum(mi.Frame3f.cos_theta(wo), 0)
                lambert = base * kd * cos_o * dr.inv_pi
                f_d = dr.select(mi.Frame3f.cos_theta(si.wi) > 0, dr.clip(lambert, 0, bsdf_val), 0)
            return f_d

        def aov_values(self, values: dict) -> list:
            """The AOV channels in ``self.layout`` order: each buffer's channels, squared for a moment."""
            aovs = []
            for name, m2, size in self.layout:
                v = values[name]
                chans = [v] if size == 1 else [v[i] for i in range(size)]
                aovs += [c * c for c in chans] if m2 else chans
            return aovs

    _CLASS[variant] = SplitIntegrator
    return SplitIntegrator


def register(mitsuba) -> None:
    """Register the ``split`` integrator plugin with Mitsuba (idempotent per variant)."""
    cls = integrator_class(mitsuba)
    if getattr(cls, "_registered", False):
        return
    mitsuba.register_integrator("split", lambda props: cls(props))
    cls._registered = True
