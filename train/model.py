"""The network: OIDN's network, frozen, with a Control Module (paper Fig. 1); where models are, save and load.

The base is OIDN's UNet (``pipeline.oidn_net``) with OIDN's weights, or an ``oidn_ft`` run's;
it never trains. It reads what OIDN reads (colour, albedo, normal in OIDN's input space) and its
output, decoded without help, is OIDN's own output: the first estimate.

The Control Module is a trainable copy of the base's encoder (``enc_conv0`` … ``enc_conv5b``, or the
large layout's ``enc_conv1a`` … ``enc_conv5b``,
initialised from the base's weights, as ControlNet copies its base), whose first convolution
reads OIDN's input plus the condition (every other buffer of the frame, the spp, which buffer
groups are present) and the diffusion state z_t, and whose levels get the timestep embedding
as a per-channel bias. Its features enter the base's decoder through zero-initialised 1×1
convolutions at every skip the decoder reads (the input, ``pool1`` … ``pool3``, the bottleneck)
and at its output:

    feats = base.encode(x)                          x: OIDN's input (frozen base, no gradient)
    x_est = base.decode(feats)                      the first estimate, OIDN's output
    r     = zero_conv(control(x ⊕ cond ⊕ z_t, t))   residuals per skip, and for the output
    x̂₀    = base.decode(feats, r) + r_output

Every zero convolution, the weights of the first convolution's extra input channels and the
timestep projections start at zero, so at initialisation x̂₀ = x_est exactly (tested): training
can only start at OIDN.

A model folder (a run ``<runs>/diffusion_spp<N>[_<name>]``, an export such as ``train/shipped``) holds
``control.safetensors`` (the Control Module), ``base.tza`` (the frozen base's float16 weights, so the
folder is self-contained, its SHA-256 in model.json) and ``model.json`` (``save`` / ``load``).
"""
from __future__ import annotations

import copy
import hashlib
import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from mcdenoise.pipeline import oidn_net, oidn_weights, runs, tza, weights
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.errors import CheckpointError
from mcdenoise.pipeline.exr import atomic_write_bytes

from .data import cond_names

EMBED = 64   # sinusoidal timestep features
FORMAT = weights.FORMATS["oidn_control"]
NETWORK = "rt_hdr_alb_nrm"      # the base of models whose model.json predates diffusion.base_network
# The denoiser shipped with the repository (base + Control Module + model card), used when a config
# has no trained run of its own (train/shipped/README.md says how it was made).
SHIPPED_MODEL = Path(__file__).resolve().parent / "shipped"


def skip_sources(layout: oidn_net.Layout) -> dict[str, str]:
    """The decoder skips the Control Module adds to, with the encoder layer whose output feeds each
    (the input skip ``x`` gets the level-0 features, as ``pool1`` does before pooling)."""
    last = [stage[-1] for stage in layout.stages]
    return {"x": last[0], "pool1": last[0], "pool2": last[1], "pool3": last[2], "bottleneck": layout.bottleneck[-1]}


def timestep_features(t: torch.Tensor, dim: int = EMBED) -> torch.Tensor:
    """Sinusoidal features (B, dim) of diffusion timesteps 0 … 999 (as diffusers' ``Timesteps``)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]
    return torch.cat([torch.sin(args), torch.cos(args)], 1)


class ControlModule(nn.Module):
    """A copy of ``base``'s encoder reading ``extra`` more input channels, with a timestep bias per level
    and zero 1×1 convolutions to the decoder's skips and output."""

    def __init__(self, base: oidn_net.UNet, extra: int):
        super().__init__()
        self.extra, self.layout = int(extra), base.layout
        self.encoder = nn.ModuleDict({n: copy.deepcopy(getattr(base, n)) for n in self.layout.encoder})
        first = self.encoder[self.layout.first]
        wide = nn.Conv2d(first.in_channels + self.extra, first.out_channels, 3, padding=1)
        with torch.no_grad():
            wide.weight.zero_()
            wide.weight[:, :first.in_channels] = first.weight
            wide.bias.copy_(first.bias)
        self.encoder[self.layout.first] = wide
        self.embed = nn.Sequential(nn.Linear(EMBED, 128), nn.SiLU())
        self.time_bias = nn.ModuleDict({n: _zero(nn.Linear(128, getattr(base, n).out_channels))
                                        for n in self.layout.encoder})
        width = {n: getattr(base, src).out_channels for n, src in skip_sources(self.layout).items()}
        self.zero = nn.ModuleDict({n: _zero(nn.Conv2d(width[n], base.in_channels if n == "x" else width[n], 1))
                                   for n in width})
        self.zero["output"] = _zero(nn.Conv2d(width["x"], base.widths[self.layout.output][0], 1))

    def _conv(self, name: str, h: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        return F.relu(self.encoder[name](h) + self.time_bias[name](emb)[:, :, None, None])

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> dict[str, torch.Tensor]:
        """Residuals for ``UNet.decode`` (``x``, ``pool1`` … ``bottleneck``) and ``output``."""
        emb = self.embed(timestep_features(t))
        feats = oidn_net.encode(self.layout, lambda name, h: self._conv(name, h, emb), x)
        feats["x"] = feats["output"] = feats["full"]
        return {n: conv(feats[n]) for n, conv in self.zero.items()}


def _zero(m: nn.Module) -> nn.Module:
    for p in m.parameters():
        nn.init.zeros_(p)
    return m


class ControlledOIDN(nn.Module):
    """Frozen OIDN base + Control Module: ``forward(x, cond, z, t) -> (x̂₀, x_est)`` in OIDN's output space.

    ``x``: OIDN's input (B, 3/6/9, H, W), ``cond``: the condition (B, C, H, W), ``z``: z_t (B, 3, H, W),
    ``t``: timesteps (B,); sides a multiple of 16. ``control=None``: the base alone (x̂₀ = x_est)."""

    multiple = oidn_net.ALIGNMENT

    def __init__(self, base: oidn_net.UNet, cond_channels: int, control: bool = True):
        super().__init__()
        self.base = base.requires_grad_(False).eval()
        self.cond_channels = int(cond_channels)
        self.control = ControlModule(base, self.cond_channels + 3) if control else None

    def train(self, mode: bool = True):
        super().train(mode)
        self.base.eval()      # frozen, whatever the caller does
        return self

    def trainable_parameters(self) -> list[nn.Parameter]:
        return list(self.control.parameters()) if self.control is not None else []

    def estimate(self, x: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """(the base's encoder features, its output: the first estimate); no gradient."""
        with torch.no_grad():
            feats = self.base.encode(x)
            return feats, self.base.decode(feats)

    def forward(self, x: torch.Tensor, cond: torch.Tensor, z: torch.Tensor, t: torch.Tensor,
                base: tuple | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``base``: ``estimate(x)`` when the caller has it already (a sampler's later steps)."""
        feats, est = base if base is not None else self.estimate(x)
        if self.control is None:
            return est, est
        r = self.control(torch.cat([x, cond, z], 1), t.expand(x.shape[0]))
        out = self.base.decode(feats, {k: v for k, v in r.items() if k != "output"}) + r["output"]
        return out, est


# ---- the base ----------------------------------------------------------------------------------


def base_blob(cfg: Config) -> tuple[bytes, str]:
    """(the base's float16 TZA blob, what it is): ``diffusion.base`` 'oidn' (OIDN's ``diffusion.base_network``,
    from ``oidn.weights`` or pyoidn), 'oidn_ft' (this config's oidn_ft run of that network, as exported) or a
    .tza file of it."""
    base, network = cfg.diffusion.base, cfg.diffusion.base_network
    if base == "oidn":
        return oidn_weights.load(network, oidn_weights.source(network, cfg.oidn.weights)), f"OIDN {network}"
    if base == "oidn_ft":
        from .oidn_ft import export_blob, load_run
        folder = runs.run_dir(cfg, "oidn_ft", variant=network)
        return export_blob(load_run(folder, cfg)[0]), f"oidn_ft run {folder} (blend {cfg.oidn_ft.blend:g})"
    return oidn_weights.load(network, base), str(base)


def clean_aux(meta: dict) -> bool:
    """Whether a model (its model.json) feeds its base prefiltered albedo and normal."""
    return oidn_weights.clean_aux(meta.get("base_network", NETWORK))


# ---- where models are --------------------------------------------------------------------------


def run_dir(cfg: Config, spp: int | str, variant: str | None = None) -> Path:
    """``diffusion_spp4``, ``diffusion_sppany``, ``diffusion_sppany_<variant>`` under ``cfg.runs``
    (``pipeline.runs.run_dir``)."""
    return runs.run_dir(cfg, "diffusion", spp, variant)


def oidn_ft_blob(folder: Path, network: str) -> Path:
    """Where a model folder (``train/shipped``, an export) keeps OIDN's ``network`` fine-tuned, the weights
    it runs on inputs without the layers its base reads; the folder may not have them."""
    return Path(folder) / "oidn_ft" / f"{network}.tza"


def find_run(cfg: Config, spp: int | str, variant: str | None = None) -> Path:
    """The trained run for ``spp``: ``diffusion_spp<N>[_variant]`` if it exists, else the spp-conditioned
    ``diffusion_sppany[_variant]`` (one model serves every sample count), else (no variant, and
    ``diffusion.shipped``) the model shipped with the repository (``SHIPPED_MODEL``); CheckpointError (a StoreError) if none."""
    named = variant if variant is not None else cfg.diffusion.name
    shipped = SHIPPED_MODEL if not named and cfg.diffusion.shipped else None
    folder = runs.find_run(cfg, "diffusion", spp, "model.json", variant, fallback=shipped)
    if folder is not None:
        return folder
    candidates = runs.run_candidates(cfg, "diffusion", spp, variant) + ([shipped] if shipped else [])
    raise CheckpointError(f"no diffusion checkpoint in {' or '.join(map(str, candidates))}: run "
                          f"`make train SPP={spp}` or `make train SPP=any`" +
                          (f" with diffusion.name={variant}" if variant else ""))


# ---- saving and loading ------------------------------------------------------------------------


def save(folder: Path, model: ControlledOIDN, blob: bytes, what: str, network: str, form, spps: list[int],
         record: dict) -> None:
    """The Control Module, the base's blob and model.json (``form``: the ``Formulation`` it was trained with)."""
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "base.tza").exists() or (folder / "base.tza").read_bytes() != blob:
        atomic_write_bytes(folder / "base.tza", lambda tmp: Path(tmp).write_bytes(blob))
    weights.save(folder, "oidn_control", model.control.state_dict(), {
        "base": "base.tza", "base_network": network, "base_what": what, "base_sha256": hashlib.sha256(blob).hexdigest(),
        "cond_channels": cond_names(), "spp": spps, "formulation": form.record(), **record}, weights="control.safetensors")


def load(folder: str | Path, device="cpu") -> tuple[ControlledOIDN, dict]:
    """(the controlled model in eval mode, model.json) of a run or an exported model folder."""
    folder = Path(folder)
    meta = weights.read_record(folder, "oidn_control", "run `make train SPP=any`")
    blob = (folder / meta["base"]).read_bytes()
    weights.check_sha256(blob, meta["base_sha256"], f"{folder / meta['base']}: the base", "restore it or retrain")
    if meta["cond_channels"] != cond_names():
        raise CheckpointError(f"{folder / 'model.json'}: trained on another condition layout "
                              f"({len(meta['cond_channels'])} channels, this code makes {len(cond_names())}); retrain")
    model = ControlledOIDN(oidn_net.UNet.from_tza(tza.read(blob, str(folder / meta["base"]))), len(cond_names()))
    model.control.load_state_dict({k: v.float() for k, v in weights.load_tensors(folder / "control.safetensors").items()})
    return model.to(device).eval(), meta
