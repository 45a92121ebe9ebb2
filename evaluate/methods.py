"""The methods the evaluator compares, each behind one small interface.

A ``Method`` has a ``name``, a ``device`` and ``denoise(buffers) -> (H, W, 3) float32 HDR``,
where ``buffers`` is what ``Store.read(scene, frame, spp)`` returns (buffer name → (H, W, C)
array, variances included). One instance serves one sample count (the Isik baseline and the
diffusion model are trained per spp, or once for every spp with ``SPP=any``). Timing, input
repair and output checks are done by the harness (``evaluate.harness.run_method``), never by a
method.

Names (``eval.methods``):

- ``noisy``: the input colour itself.
- ``oidn``: Intel Open Image Denoise 2.5 (``train.oidn``: filter RT, HDR, quality high) with
  albedo and normal; ``oidn_albedo``: colour and albedo; ``oidn_color``: colour only;
  ``oidn_prefilter``: OIDN's mode for final frames with noisy aux (albedo and normal denoised by its
  aux networks first, then ``cleanAux``: its ``rt_hdr_calb_cnrm_large`` network at quality high),
  three filter runs.
- ``oidn_ft``: OIDN's network fine-tuned on the store (``train.baselines.oidn_ft``, run
  ``runs/<...>/oidn_ft_rt_hdr_alb_nrm``, ``make train MODEL=oidn_ft SPP=any``; one model for every
  spp), run by OIDN itself with the exported float16 weights (``train.oidn``'s ``weights``), at
  ``oidn_ft.blend``; ``oidn_ft_albedo`` and ``oidn_ft_color``: the colour + albedo and the colour-only
  networks' runs (``oidn_ft_rt_hdr_alb``, ``oidn_ft_rt_hdr``); ``oidn_ft_prefilter``: OIDN's final-frame
  network fine-tuned (``oidn_ft_rt_hdr_calb_cnrm_large``), run as ``oidn_prefilter`` runs. Each row without a run of its own runs the
  weights shipped with the model (``train/shipped/oidn_ft/<network>.tza``, fine-tuned on the ship data;
  ``ours`` runs the two without normal on inputs without normal, or without albedo and normal).
- ``isik``: the affinity-network baseline of ``runs/<...>/isik_spp<N>`` (``make train MODEL=isik``),
  or where that run does not exist the spp-conditioned ``isik_sppany`` (``SPP=any``) if it was
  trained at N spp.
- ``afgsa``: AFGSA (Yu et al. 2021, ``train.baselines.afgsa``) of ``runs/<...>/afgsa_spp<N>``, else of the
  all-spp run ``afgsa_sppany`` (``make train MODEL=afgsa SPP=N|any``); Isik and AFGSA both run
  through ``clean.apply.denoise`` (tiled).
- ``ours``: the diffusion denoiser of ``train.infer`` (run ``diffusion_spp<N>``, else the
  spp-conditioned ``diffusion_sppany``, else the model shipped in ``train/shipped``; the row's
  weights column says which), sampled as its model was configured; ``base_only``: the same base
  without its Control Module (the paper's ablation row: OIDN's network as the model holds it).
  Options follow the family, separated by ``_``: first an optional run variant (``ours_large``: run
  ``diffusion_spp<N>_large``, trained with ``diffusion.name=large``), then any of ``sN`` (N sampler
  steps), ``skipN`` (skip the first N), ``kN`` (the mean of N samples), ``noise`` / ``render`` /
  ``estimate`` (where sampling starts), ``strengthN`` (N %: the base's output plus that fraction of
  what the Control Module changes). E.g. ``ours_s1``, ``ours_s3_k4``, ``base_only_s1``,
  ``ours_strength50``.
- ``_xN`` after any name (N in 2, 4, 8; last): that method's self-ensemble over N flipped and transposed
  copies of the frame (``train.infer.self_ensemble``), at N times its cost, e.g. ``oidn_x8``, ``ours_x8``.
  These are looked up lazily, as

      from mcdenoise.train.infer import load_denoiser
      den = load_denoiser(folder, device=device, base_only=False)
      hdr = den.denoise(buffers, spp=spp, steps=N, samples=K, seed=cfg.eval.seed)

  A missing module or checkpoint makes the method *not available* with the reason (a row in the
  table), never a crash and never made-up numbers. Every trained method's row names the weights it
  ran (``checkpoint``: a run folder, or what it took from ``train/shipped``).
"""
from __future__ import annotations

import re
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcdenoise.pipeline.config import Config, ConfigError
from mcdenoise.pipeline.errors import PipelineError
from mcdenoise.pipeline.exr import StoreError
from mcdenoise.train import infer

# Diffusion families: family -> without the Control Module. Name tokens after the family select the
# run variant and the sampling (see the module docstring).
_DIFFUSION = {"ours": False, "base_only": True}
# OIDN families -> the network OIDN runs; oidn_ft families -> the network their run fine-tuned
OIDN_STOCK = {"oidn": "rt_hdr_alb_nrm", "oidn_albedo": "rt_hdr_alb", "oidn_color": "rt_hdr",
              "oidn_prefilter": "rt_hdr_calb_cnrm"}
OIDN_FT = {"oidn_ft": "rt_hdr_alb_nrm", "oidn_ft_albedo": "rt_hdr_alb", "oidn_ft_color": "rt_hdr",
           "oidn_ft_prefilter": "rt_hdr_calb_cnrm_large"}
FAMILIES = ("noisy", *OIDN_STOCK, *OIDN_FT, "isik", "afgsa", *_DIFFUSION)
_TOKEN = re.compile(r"^(?:s(?P<steps>\d+)|skip(?P<skip>\d+)|k(?P<samples>\d+)|x(?P<ensemble>\d+)|"
                    r"(?P<start>noise|render|estimate)|strength(?P<strength>\d+))$")
LABELS = {"noisy": "Noisy input", "oidn": "OIDN (colour+albedo+normal)", "oidn_albedo": "OIDN (colour+albedo)",
          "oidn_color": "OIDN (colour only)",
          "oidn_prefilter": "OIDN (colour+prefiltered albedo+normal, cleanAux)",
          "oidn_ft": "OIDN fine-tuned on our data (colour+albedo+normal)",
          "oidn_ft_albedo": "OIDN fine-tuned on our data (colour+albedo)",
          "oidn_ft_color": "OIDN fine-tuned on our data (colour only)",
          "oidn_ft_prefilter": "OIDN's final-frame network fine-tuned on our data (prefiltered aux, cleanAux)",
          "isik": "Isik et al.", "afgsa": "AFGSA (Yu et al. 2021)",
          "ours": "Ours (diffusion)", "base_only": "Base only (no Control Module)"}


class MethodUnavailable(PipelineError):
    """The method cannot run here (missing package, module or checkpoint); the message says why."""


@dataclass(frozen=True)
class Spec:
    """A parsed method name: ``family[_variant][_sN][_skipN][_kN][_noise|_render|_estimate][_strengthN][_xN]``."""
    family: str
    variant: str = ""
    steps: int | None = None
    skip: int | None = None
    samples: int = 1
    start: str | None = None
    ensemble: int = 1
    strength: float | None = None     # percent in the name (strength50 = 0.5); None: the model's own


def parse(name: str, key: str = "eval.methods", also: tuple[str, ...] = ()) -> Spec:
    """``ours_large_skip1`` → Spec("ours", "large", skip=1); unknown names: ConfigError naming the config ``key``
    (and the names ``also`` valid there among the known ones)."""
    family = next((f for f in sorted(FAMILIES, key=len, reverse=True)
                   if name == f or name.startswith(f + "_")), None)
    if family is None:
        raise ConfigError(f"{key}: unknown method {name!r} (known: {', '.join((*FAMILIES, *also))}, and "
                          "<ours|base_only>[_variant][_sN][_skipN][_kN][_noise|_render|_estimate][_strengthN])")
    tokens = [t for t in name[len(family):].split("_") if t]
    if family not in _DIFFUSION and any(not re.fullmatch(r"x\d+", t) for t in tokens):
        raise ConfigError(f"{key}: {name!r}: only ours and base_only take options other than xN")
    fields: dict = {}
    for i, tok in enumerate(tokens):
        m = _TOKEN.match(tok)
        if m is None:
            if i != 0 or not re.fullmatch(r"[a-z][a-z0-9-]*", tok):
                raise ConfigError(f"{key}: {name!r}: unknown option {tok!r} (a run variant comes first; "
                                  "options are sN, skipN, kN, noise, render, estimate, strengthN)")
            fields["variant"] = tok
            continue
        for option, value in m.groupdict().items():
            if value is not None:
                fields[option] = (int(value) if option in ("steps", "skip", "samples", "ensemble")
                                  else int(value) / 100 if option == "strength" else value)
    spec = Spec(family, **fields)
    if spec.strength is not None and spec.strength > 1:
        raise ConfigError(f"{key}: {name!r}: strengthN is a percentage from 0 to 100")
    if spec.samples < 1 or (spec.steps is not None and spec.steps < 1):
        raise ConfigError(f"{key}: {name!r}: steps and samples must be at least 1")
    if spec.ensemble not in infer.ENSEMBLE_SIZES or (spec.ensemble > 1 and tokens[-1] != f"x{spec.ensemble}"):
        raise ConfigError(f"{key}: {name!r}: a self-ensemble xN comes last, N in {infer.ENSEMBLE_SIZES}")
    return spec


def curve_kind(name: str) -> str:
    """The name without its step options (sN, skipN): rows of one kind form one curve over step counts."""
    spec = parse(name)
    return "_".join([spec.family] + [p for p in (spec.variant, spec.start) if p]
                    + ([f"k{spec.samples}"] if spec.samples > 1 else [])
                    + ([f"strength{round(spec.strength * 100)}"] if spec.strength is not None else [])
                    + ([f"x{spec.ensemble}"] if spec.ensemble > 1 else []))


def label(name: str) -> str:
    spec = parse(name)
    parts = [LABELS[spec.family] + (f" [{spec.variant}]" if spec.variant else "")]
    if spec.steps is not None:
        parts.append(f"{spec.steps} step{'s' if spec.steps > 1 else ''}")
    if spec.skip:
        parts.append(f"{spec.skip} skipped")
    if spec.start:
        parts.append(f"from the {spec.start}")
    if spec.samples > 1:
        parts.append(f"mean of {spec.samples} samples")
    if spec.strength is not None:
        parts.append(f"strength {spec.strength:g}")
    if spec.ensemble > 1:
        parts.append(f"self-ensemble of {spec.ensemble} flips/transposes")
    return ", ".join(parts)


class Method(ABC):
    """One denoiser at one sample count."""

    name: str = ""
    device: str = "cpu"
    checkpoint: str = ""          # the weights a method ran (a run folder, train/shipped/...), its table row's weights

    @abstractmethod
    def denoise(self, buffers: dict[str, np.ndarray]) -> np.ndarray:
        """HDR radiance (H, W, 3) float32 from one frame's buffers."""

    def set_frame(self, store, key) -> None:
        """Called before ``denoise`` with the frame's store and key, for methods that need more than
        its buffers (the diffusion model reads the camera to put normals in camera space)."""

    def note(self) -> str:
        """What the last ``denoise`` did beyond denoising (clamped its range, returned black), or ''."""
        return ""

    def uncertainty(self) -> np.ndarray | None:
        """The last ``denoise``'s own per-pixel standard deviation (H, W, 3), for methods that give one."""
        return None


@dataclass
class Noisy(Method):
    name: str = "noisy"
    device: str = "-"

    def denoise(self, buffers):
        return np.array(buffers["color"], dtype=np.float32)


@dataclass
class OIDN(Method):
    """OIDN on colour and the aux layers of ``network`` (``oidn.network_aux``), with its built-in
    weights or, for the oidn_ft rows, ``weights`` (the float16 TZA blob of an oidn_ft run or shipped file);
    a ``_calb_cnrm`` network gets its aux prefiltered by OIDN (``train.oidn``'s ``clean_aux``)."""
    name: str = "oidn"
    network: str = "rt_hdr_alb_nrm"
    weights: bytes | None = None
    quality: str = "high"
    device: str = "cpu"
    checkpoint: str = ""

    def __post_init__(self):
        from mcdenoise.train import oidn
        why = oidn.available()
        if why:
            raise MethodUnavailable(why)
        if self.weights is None and not self.checkpoint:
            self.checkpoint = "OIDN's built-in weights"

    def denoise(self, buffers):
        from mcdenoise.train import oidn
        return oidn.denoise(_layers_of(self.network, buffers), quality=self.quality, weights=self.weights,
                            clean_aux="_calb_cnrm" in self.network)


def _layers_of(network: str, buffers: dict) -> dict:
    """The buffers an OIDN network reads that the frame has: colour and its aux layers, nothing else."""
    from mcdenoise.train import oidn
    return {k: buffers[k] for k in ("color", *oidn.network_aux(network)) if k in buffers}


@dataclass
class CleanNet(Method):
    """A network on ``clean.data.frame_inputs`` (the Isik baseline, AFGSA), tiled by ``clean.apply``."""

    model: object = None
    tile: int = 512
    name: str = "isik"
    device: str = "cpu"
    checkpoint: str = ""          # isik_spp<N>, or isik_sppany serving N

    def denoise(self, buffers):
        from mcdenoise.clean.apply import denoise
        from mcdenoise.clean.data import frame_inputs

        inputs, radiance = frame_inputs(buffers)
        return denoise(self.model, inputs, radiance, tile=self.tile, device=self.device)


@dataclass
class Diffusion(Method):
    """``ours``/``base_only`` through ``train.infer``'s denoiser object, sampled as ``spec`` says."""

    denoiser: object = None
    spp: int = 4
    spec: Spec = None
    seed: int = 0
    name: str = "ours"
    device: str = "cpu"
    checkpoint: str = ""          # the model folder it loaded (a run folder or train/shipped) and its base
    last_std: object = None       # per-pixel std of the last call's samples (kN with N > 1)

    def note(self) -> str:
        den = self.denoiser
        if getattr(den, "last_black", False):
            return "input black everywhere: returned black"
        if getattr(den, "last_estimate_only", False):
            if getattr(den, "fallback", ""):
                return f"no albedo/normal in the input: returned {den.fallback} on the colour"
            return "no renderer variance/albedo/normal in the input: returned the first estimate (OIDN)"
        if getattr(den, "last_base_only", False):
            return "colour, albedo and normal only: returned the model's base alone (control_without_groups)"
        n = getattr(den, "last_clamped", 0)
        return f"{n} {den.clamp_note}" if n else ""

    def uncertainty(self):
        return self.last_std

    def denoise(self, buffers, history=None):
        """``history``: (previous output warped into this frame, validity), for a model that reads the past."""
        s = self.spec
        out, std = self.denoiser.denoise(buffers, spp=self.spp, skip=s.skip, seed=self.seed, steps=s.steps,
                                         start=s.start, samples=s.samples, with_std=True, strength=s.strength,
                                         history=history)
        self.last_std = std if s.samples > 1 else None
        return np.asarray(out, dtype=np.float32)


@dataclass
class SelfEnsemble(Method):
    """``inner`` on ``n`` flipped and transposed copies of the frame, turned back and averaged
    (``train.infer.self_ensemble``): ``n`` times its cost. No per-pixel uncertainty of its own."""

    inner: Method = None
    n: int = 8
    name: str = ""
    device: str = "cpu"
    checkpoint: str = ""

    def __post_init__(self):
        self.device, self.checkpoint = self.inner.device, self.inner.checkpoint

    def set_frame(self, store, key) -> None:
        self.inner.set_frame(store, key)

    def note(self) -> str:
        return self.inner.note()

    def denoise(self, buffers):
        return infer.self_ensemble(self.inner.denoise, buffers, self.n)


@dataclass
class Loader:
    """Builds methods for one config; loaded models are shared (ours and ours_skipN use one model)."""

    cfg: Config
    _models: dict = field(default_factory=dict)

    def device(self) -> str:
        from mcdenoise.pipeline.config import pick_device
        return str(pick_device(self.cfg.eval.device))

    def load(self, name: str, spp: int) -> Method:
        """The method ``name`` at ``spp``; raises ``MethodUnavailable`` with the reason."""
        spec = parse(name)
        if spec.ensemble > 1:
            inner = self.load(name.removesuffix(f"_x{spec.ensemble}"), spp)
            return SelfEnsemble(inner=inner, n=spec.ensemble, name=name)
        if spec.family == "noisy":
            return Noisy()
        if spec.family in OIDN_STOCK:
            return OIDN(name=name, network=OIDN_STOCK[spec.family])
        if spec.family in OIDN_FT:
            return self._oidn_ft(spec.family)
        if spec.family in ("isik", "afgsa"):
            return self._clean_net(spec.family, spp)
        return self._diffusion(name, spec, spp)

    def _oidn_ft(self, family: str) -> Method:
        from mcdenoise.pipeline.config import run_dir
        from mcdenoise.train.baselines.oidn_ft import export_blob, load_run
        from mcdenoise.train.model import SHIPPED_MODEL, oidn_ft_blob

        folder = run_dir(self.cfg, "oidn_ft", variant=OIDN_FT[family])
        trained = (folder / "model.safetensors").exists()
        # no run of its own: the weights shipped with the denoiser, as the ours rows fall back to it
        shipped = oidn_ft_blob(SHIPPED_MODEL, OIDN_FT[family]) if self.cfg.diffusion.shipped else None
        if not trained and not (shipped and shipped.exists()):
            raise MethodUnavailable(f"no oidn_ft run in {folder}: run `make train MODEL=oidn_ft SPP=any"
                                    + ("`" if family == "oidn_ft" else f" oidn_ft.network={OIDN_FT[family]}`"))
        if not trained:
            return OIDN(weights=shipped.read_bytes(), network=OIDN_FT[family], name=family,
                        checkpoint=weights_name(shipped))
        key = ("oidn_ft", str(folder))
        if key not in self._models:
            try:
                self._models[key] = export_blob(load_run(folder, self.cfg)[0])
            except (OSError, PipelineError, ValueError, KeyError) as exc:
                raise MethodUnavailable(f"cannot load the oidn_ft run {folder}: {type(exc).__name__}: {exc}") from None
        return OIDN(weights=self._models[key], network=OIDN_FT[family], name=family, checkpoint=weights_name(folder))

    def _clean_net(self, family: str, spp: int) -> Method:
        from mcdenoise.clean.model import load_model as load_isik
        from mcdenoise.clean.train import baseline_checkpoint, run_dir
        from mcdenoise.pipeline.config import find_run, run_candidates
        from mcdenoise.train.baselines.afgsa import load_model as load_afgsa

        if family == "isik":
            folder = baseline_checkpoint(self.cfg, spp)
            if folder is None:
                raise MethodUnavailable(f"no Isik checkpoint in {run_dir(self.cfg, 'baseline', spp)}, and "
                                        f"{run_dir(self.cfg, 'baseline', 'any')} has none trained at {spp} spp: run "
                                        f"`make train MODEL=isik SPP={spp}` (or SPP=any)")
            tile, load = self.cfg.clean.tile, load_isik
        else:
            folder = find_run(self.cfg, "afgsa", spp, "model.safetensors")
            if folder is None:
                searched = " or ".join(map(str, run_candidates(self.cfg, "afgsa", spp)))
                raise MethodUnavailable(f"no AFGSA checkpoint in {searched}: run "
                                        f"`make train MODEL=afgsa SPP={spp}` (or SPP=any)")
            tile, load = self.cfg.afgsa.tile, load_afgsa
        # One spp-conditioned model serves every spp: load it once.
        if folder not in self._models:
            self._models[folder] = load(folder, self.device())[0]
        return CleanNet(model=self._models[folder], tile=tile, name=family, device=self.device(),
                        checkpoint=weights_name(folder))

    def diffusion_folder(self, spp: int, variant: str) -> Path:
        """``train.model.find_run``: the run for ``spp``, else the spp-conditioned one; a method without a variant
        (``ours``) takes the config's ``diffusion.name``, as training named the run."""
        from mcdenoise.train.model import find_run

        try:
            return find_run(self.cfg, spp, variant or None)
        except StoreError as exc:
            raise MethodUnavailable(str(exc)) from None

    def _diffusion(self, name: str, spec: Spec, spp: int) -> Method:
        base_only = _DIFFUSION[spec.family]
        folder = self.diffusion_folder(spp, spec.variant)
        key = ("diffusion", str(folder), base_only)
        if key not in self._models:
            try:
                from mcdenoise.train.infer import load_denoiser
                self._models[key] = load_denoiser(folder, device=self.device(), base_only=base_only)
            except (OSError, StoreError, ConfigError, ValueError, KeyError) as exc:
                raise MethodUnavailable(f"cannot load the diffusion model from {folder}: "
                                        f"{type(exc).__name__}: {exc}") from None
        den = self._models[key]
        if not 0 <= (spec.skip or 0) < (spec.steps or den.formulation.steps):
            raise MethodUnavailable(f"{name}: skip must be below the number of steps")
        what = "its base alone:" if base_only else "Control Module on"
        return Diffusion(denoiser=den, spp=spp, spec=spec, seed=self.cfg.eval.seed, name=name, device=self.device(),
                         checkpoint=f"{weights_name(folder)} ({what} {den.meta.get('base_what', 'OIDN')})")


def weights_name(path: Path) -> str:
    """How a row names the weights it ran: ``train/shipped/...`` for what ships with the repository, else the
    path as found (a run folder under the config's ``runs``)."""
    from mcdenoise.train.model import SHIPPED_MODEL

    path = Path(path)
    try:
        return str(Path("train/shipped") / path.resolve().relative_to(SHIPPED_MODEL))
    except ValueError:
        return str(path)


def check_names(names: list[str], key: str = "eval.methods", also: tuple[str, ...] = ()) -> None:
    """ConfigError naming ``key`` for an unknown or repeated method name (``also``: names valid there besides
    the per-frame methods)."""
    for name in names:
        if name not in also:
            parse(name, key, also)
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"{key}: {', '.join(dup)} listed twice")
