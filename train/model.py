"""The network: OIDN's network in PyTorch, frozen, with a Control Module (paper Fig. 1); its input; where models
are, save and load. Read top to bottom: OIDN's HDR processing, its aux prefilter, the network's input, OIDN's
UNet, the Control Module on it, then model folders.

**OIDN's network** (equal to pyoidn's output: ``tests/test_oidn_net.py``), built from a TZA archive's shapes
(``pipeline.weights``, ``train.oidn``), so the colour, +albedo and +albedo+normal networks (3/6/9 input
channels), their ``_small`` variants and the ``_large`` layout (``rt_hdr_calb_cnrm_large``, what OIDN runs at
quality high on prefiltered aux) all load. The UNet (OIDN's ``training/model.py``, ``UNet`` and ``UNetLarge``;
``Layout`` names the layers): 3×3 convolutions with padding 1, each followed by a ReLU except the last; five
encoder levels with 2×2 max pooling after the first four (one or two convolutions each; the large layout always
two, and wider); a decoder of nearest ×2 upsampling, concatenation ``[upsampled, skip]`` (the order matters)
and two convolutions per level, the last level concatenating the network input itself, then the output
convolution. Its HDR processing (OIDN's core: ``autoexposure``, ``network_input``, ``network_output``) is
described where it is defined.

**The network's input** (``inputs``, the one place every caller encodes a frame): OIDN's own input ``x``
(colour × OIDN's autoexposure in PU, albedo, normal; prefiltered by OIDN's aux networks for a ``_calb_cnrm``
base) and the condition ``cond``: ``pipeline.schema``'s feature table in OIDN's space (each radiance buffer as
PU(radiance × the same exposure), normals as stored, depth relative, the material features, one
relative-variance channel per buffer), the spp map log2(spp)/6, and one constant map per buffer group saying
whether the input had it (``GROUPS``). A group an input lacks (an EXR from another renderer has no variances,
no radiance split, no material buffers) is its background value, 0, with its presence map 0: the network is
trained with such inputs (``train.data.DROPOUT``), so it serves them rather than falling back. A model that reads
the past (``reads_history``: its model.json's ``cond_channels`` have the history's) has one more group,
``history``: the previous frame's output warped into this one as PU(output × this frame's exposure), zero where
the warp is invalid, the validity, and ``has.history``; absent (a first frame) it is zero like any other group.
A model without it keeps its condition channel for channel (``cond_names()``; ``cond_names(True)`` is the longer one).

**The base** is OIDN's UNet with OIDN's weights, or an ``oidn_ft`` run's; it never trains. It reads what OIDN
reads and its output, decoded without help, is OIDN's own output: the first estimate.

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
import functools
import hashlib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from mcdenoise.pipeline import config as config_mod, schema, weights
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.errors import CheckpointError, StoreError, WeightsError
from mcdenoise.pipeline.exr import atomic_write_bytes, read_json
from mcdenoise.pipeline.weights import TZATensor, read_tza

from . import oidn

EMBED = 64   # sinusoidal timestep features
FORMAT = weights.FORMATS["oidn_control"]
NETWORK = "rt_hdr_alb_nrm"      # the base of models whose model.json predates diffusion.base_network
# The denoiser shipped with the repository (base + Control Module + model card), used when a config
# has no trained run of its own (train/shipped/README.md says how it was made).
SHIPPED_MODEL = Path(__file__).resolve().parent / "shipped"


# ---- OIDN's HDR processing (its core's input_process / output_process / autoexposure) ---------------
# input: colour × scale, NaN → 0, clamped ≥ 0, then the PU transfer normalised so that 65504 maps to 1
# (``to_pu``); albedo NaN → 0 and clamped to [0, 1]; normal NaN → 0, clamped to [−1, 1], then n·0.5 + 0.5;
# zero padding at the bottom and right to a multiple of 16. Output: NaN → 0, clamped ≥ 0, the inverse PU
# transfer (``from_pu``), divided by the scale. ``autoexposure``: 0.18 / 2^(mean log2 of the mean luminance
# of ~16×16 bins whose mean is above 1e-8); 1 if none is. The network's output space (PU of the exposed
# radiance) is where OIDN's training kit puts its loss, and where ours is.
ALIGNMENT = 16            # input sides are padded to a multiple of this (four 2×2 poolings)
HDR_MAX = 65504.0         # float16's largest value: PU(HDR_MAX) is normalised to 1

# PU2 fit normalised at 100 cd/m² (Aydin et al. 2008), OIDN's core/color.h.
PU_A, PU_B, PU_C, PU_D = 1.41283765e+03, 1.64593172e+00, 4.31384981e-01, -2.94139609e-03
PU_E, PU_F, PU_G = 1.92653254e-01, 6.26026094e-03, 9.98620152e-01
PU_Y0, PU_Y1 = 1.57945760e-06, 3.22087631e-02
PU_X0, PU_X1 = 2.23151711e-03, 3.70974749e-01

LUMINANCE = (0.212671, 0.715160, 0.072169)
AUTOEXPOSURE_BIN, AUTOEXPOSURE_KEY, AUTOEXPOSURE_EPS = 16, 0.18, 1e-8


def _pu_curve(y: torch.Tensor) -> torch.Tensor:
    return torch.where(y <= PU_Y0, PU_A * y,
                       torch.where(y <= PU_Y1, PU_B * y.clamp(min=PU_Y0) ** PU_C + PU_D,
                                   PU_E * torch.log(y.clamp(min=PU_Y1) + PU_F) + PU_G))


def _pu_curve_inverse(x: torch.Tensor) -> torch.Tensor:
    return torch.where(x <= PU_X0, x / PU_A,
                       torch.where(x <= PU_X1, ((x.clamp(min=PU_X0) - PU_D) / PU_B) ** (1.0 / PU_C),
                                   torch.exp((x.clamp(min=PU_X1) - PU_G) / PU_E) - PU_F))


PU_NORM = 1.0 / float(_pu_curve(torch.tensor(HDR_MAX, dtype=torch.float64)))


def to_pu(y: torch.Tensor) -> torch.Tensor:
    """OIDN's HDR transfer: PU(y) / PU(65504), for exposed radiance y ≥ 0 (0 → 0, 65504 → 1)."""
    return _pu_curve(y) * PU_NORM


def from_pu(x: torch.Tensor) -> torch.Tensor:
    """The inverse of ``to_pu`` (for x ≥ 0)."""
    return _pu_curve_inverse(x / PU_NORM)


def autoexposure(color: np.ndarray) -> float:
    """OIDN's exposure of an (H, W, 3) HDR image: 0.18 over the geometric mean of its bins' mean luminance."""
    c = np.nan_to_num(np.asarray(color, np.float32)[..., :3], nan=0.0, posinf=np.finfo(np.float32).max)
    lum = np.maximum(c, 0.0) @ np.asarray(LUMINANCE, np.float32)
    H, W = lum.shape
    nh, nw = -(-H // AUTOEXPOSURE_BIN), -(-W // AUTOEXPOSURE_BIN)
    hs = [i * H // nh for i in range(nh + 1)]
    ws = [j * W // nw for j in range(nw + 1)]
    bins = np.array([[lum[hs[i]:hs[i + 1], ws[j]:ws[j + 1]].mean() for j in range(nw)] for i in range(nh)])
    bins = bins[bins > AUTOEXPOSURE_EPS]
    if bins.size == 0:
        return 1.0
    return float(np.float32(AUTOEXPOSURE_KEY) / np.exp2(np.log2(bins.astype(np.float32)).mean(dtype=np.float32)))


def _chw(image: np.ndarray | torch.Tensor) -> torch.Tensor:
    t = torch.as_tensor(np.ascontiguousarray(image, dtype=np.float32)) if isinstance(image, np.ndarray) else image
    return torch.nan_to_num(t.float(), nan=0.0).permute(2, 0, 1)


def network_input(color, albedo=None, normal=None, scale: float = 1.0) -> torch.Tensor:
    """(1, C, H', W') input of OIDN's network from (H, W, 3) images (albedo and normal optional),
    padded with zeros at the bottom and right to a multiple of ``ALIGNMENT``."""
    parts = [to_pu(torch.nan_to_num(_chw(color) * scale, nan=0.0).clamp(min=0.0))]
    if albedo is not None:
        parts.append(_chw(albedo).clamp(0.0, 1.0))
    if normal is not None:
        parts.append(_chw(normal).clamp(-1.0, 1.0) * 0.5 + 0.5)
    x = torch.cat(parts, 0)[None]
    H, W = x.shape[-2:]
    return F.pad(x, (0, -W % ALIGNMENT, 0, -H % ALIGNMENT))


def network_output(y: torch.Tensor, scale: float, size: tuple[int, int] | None = None) -> torch.Tensor:
    """HDR radiance from the network's output (B, 3, H', W'): sanitised, inverse PU, divided by
    ``scale``; cropped to ``size`` = (H, W) when given."""
    if size is not None:
        y = y[..., :size[0], :size[1]]
    out = from_pu(torch.nan_to_num(y, nan=0.0).clamp(min=0.0))
    return out * (1.0 / scale if scale != 0 else 0.0)


# ---- the aux prefilter (OIDN's final-frame mode) ------------------------------------------------
# OIDN denoises a noisy albedo or normal with an RT filter given only that image. At quality high it
# runs ``rt_alb_large`` / ``rt_nrm_large``; the albedo goes through the sRGB transfer (it is an LDR
# image) and the normal through n·0.5 + 0.5, both inverted on the way out. Measured against pyoidn
# 2.5.1: 132 dB (albedo) and 131 dB (normal) PSNR (tests/test_oidn_net.py).
AUX_NETWORKS = {"albedo": "rt_alb_large", "normal": "rt_nrm_large"}


def srgb(x: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer (linear → encoded), for x in [0, 1]."""
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def srgb_inverse(x: torch.Tensor) -> torch.Tensor:
    """The inverse of ``srgb`` (encoded → linear), for x in [0, 1]."""
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp(min=0.04045) + 0.055) / 1.055) ** 2.4)


@torch.no_grad()
def prefilter(net, image: torch.Tensor, kind: str) -> torch.Tensor:
    """An aux image (B, 3, H, W) on any device, denoised by OIDN's aux network ``net`` for ``kind``
    ('albedo' in [0, 1], 'normal' in [−1, 1]; NaN as 0) as OIDN's filter does; same shape and range."""
    H, W = image.shape[-2:]
    image = torch.nan_to_num(image.float(), nan=0.0)
    x = srgb(image.clamp(0.0, 1.0)) if kind == "albedo" else image.clamp(-1.0, 1.0) * 0.5 + 0.5
    y = net(F.pad(x, (0, -W % ALIGNMENT, 0, -H % ALIGNMENT)))[..., :H, :W].float().clamp(0.0, 1.0)
    return srgb_inverse(y) if kind == "albedo" else y * 2.0 - 1.0


def prefilter_aux_twin(albedo: np.ndarray, normal: np.ndarray | None, device: str | None = None
                       ) -> tuple[np.ndarray, np.ndarray | None]:
    """``train.oidn.prefilter_aux`` (quality high) run in PyTorch by OIDN's aux networks on ``device`` (default: CUDA
    if there is one): the way on a GPU, and where pyoidn is not installed."""
    albedo = np.ascontiguousarray(np.clip(np.nan_to_num(albedo), 0, 1), dtype=np.float32)
    device = device or _torch_device()
    if normal is not None:
        normal = np.ascontiguousarray(np.clip(np.nan_to_num(normal), -1, 1), dtype=np.float32)
    return _prefilter_twin(albedo, device), None if normal is None else _prefilter_twin(normal, device, "normal")


def _torch_device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def _prefilter_twin(image: np.ndarray, device: str, kind: str = "albedo") -> np.ndarray:
    net = _aux_net(kind, str(device))
    x = torch.from_numpy(image).permute(2, 0, 1)[None].to(device)
    return prefilter(net, x, kind)[0].permute(1, 2, 0).cpu().numpy()


@functools.cache
def _aux_net(kind: str, device: str):
    name = AUX_NETWORKS[kind]
    return load_unet(name, oidn.weights_source(name, oidn.default_folder())).to(device).eval()


# ---- the network's input: OIDN's, and the condition ------------------------------------------------
# Buffer groups an input may lack, each with a presence map in the condition. ``history`` is read only by
# a model that reads the past (``reads_history``): the previous frame's output warped into this one
# (``history``, (H, W, 3) HDR) and where that warp is valid (``history_valid``, (H, W) or (H, W, 1)).
HISTORY_BUFFERS = ("history", "history_valid")
GROUPS = {
    "variance": tuple(schema.variance_name(b.name) for b in schema.BUFFERS),
    "components": schema.RADIANCE_COMPONENTS,
    "materials": ("depth", "roughness", "metallic", "transmission"),
    "history": HISTORY_BUFFERS,
}
# The history's condition channels: PU(history × this frame's exposure) × valid, then valid.
HISTORY_CHANNELS = ("history.R", "history.G", "history.B", "history.valid")


def groups(history: bool = False) -> list[str]:
    """The groups of ``GROUPS`` a model's condition has: all but ``history`` unless it reads the past
    (a model without it keeps the condition layout it was trained with, channel for channel)."""
    return [g for g in GROUPS if history or g != "history"]


def _pu(x: np.ndarray, scale: float) -> np.ndarray:
    return to_pu(torch.from_numpy(np.maximum(np.nan_to_num(x, nan=0.0), 0.0) * scale)).numpy()


def _encoding(scale: float) -> schema.Encoding:
    return schema.Encoding(radiance=functools.partial(_pu, scale=scale), spp=True)


def cond_names(history: bool = False) -> list[str]:
    """One name per condition channel: the feature table, ``spp``, the history's channels (a model that reads
    the past), then ``has.<group>``."""
    return (schema.names(_encoding(1.0)) + (list(HISTORY_CHANNELS) if history else [])
            + [f"has.{g}" for g in groups(history)])


def present(buffers: dict) -> dict[str, bool]:
    """Which of ``GROUPS`` an input has (all of a group's buffers)."""
    return {g: all(k in buffers for k in keys) for g, keys in GROUPS.items()}


def inputs(buffers: dict[str, np.ndarray], spp: int, aux: tuple[str, ...] = ("albedo", "normal"),
           clean_aux: bool = False, aux_device: str | None = None, history: bool = False
           ) -> tuple[np.ndarray, np.ndarray, float]:
    """(OIDN's input (3 + 3·len(aux), H', W'), the condition (C, H', W'), the exposure): float32, padded
    at the bottom and right to a multiple of 16 as OIDN pads. A group the input lacks is dropped whole.
    ``clean_aux``: OIDN's input has albedo and normal prefiltered by OIDN's aux networks (the base is a
    ``_calb_cnrm`` network), on the torch device ``aux_device`` if given (else pyoidn's); the condition keeps
    them as rendered. ``history``: the condition of a model that reads the past (``cond_names(True)``), its
    history channels from ``buffers``' ``history``/``history_valid`` (``history_channels``); without it the
    history buffers are ignored."""
    have = {g: h for g, h in present(buffers).items() if g in groups(history)}
    keep = {k: v for k, v in buffers.items() if not any(k in GROUPS[g] and not h for g, h in have.items())
            and (history or k not in HISTORY_BUFFERS)}
    scale = autoexposure(keep["color"])
    missing = [a for a in aux if a not in keep]
    if missing:
        raise StoreError(f"the OIDN-based denoiser needs {', '.join(missing)} (OIDN's network for these inputs "
                         "reads them)")
    net_aux = [keep[a] for a in aux]
    if clean_aux and aux_device is None and oidn.available() is None:
        net_aux = list(oidn.prefilter_aux(keep["albedo"], keep["normal"]))
    elif clean_aux:     # on a GPU, or without pyoidn: OIDN's aux networks in PyTorch
        net_aux = list(prefilter_aux_twin(keep["albedo"], keep["normal"], aux_device))
    x = network_input(keep["color"], *net_aux, scale=scale)[0].numpy()
    cond = schema.encode(keep, _encoding(scale), spp)
    if history:
        cond = np.concatenate([cond, history_channels(keep.get("history"), keep.get("history_valid"), scale,
                                                      cond.shape[1:])], 0)
    flags = np.broadcast_to(np.array([float(h) for h in have.values()], np.float32)[:, None, None],
                            (len(have), *cond.shape[1:]))
    cond = np.concatenate([cond, flags], 0)
    H, W = cond.shape[1:]
    cond = np.pad(cond, ((0, 0), (0, -H % ALIGNMENT), (0, -W % ALIGNMENT)))
    return x, cond.astype(np.float32), scale


def history_channels(history: np.ndarray | None, valid: np.ndarray | None, scale: float,
                     size: tuple[int, int]) -> np.ndarray:
    """(4, H, W) float32: the warped previous output encoded as the other radiance conditions (PU of it at
    this frame's exposure ``scale``, so the network compares it with this frame's colour in one space), zero
    where it is not valid, then the validity; all zero without a history (the first frame)."""
    if history is None:
        return np.zeros((len(HISTORY_CHANNELS), *size), np.float32)
    keep = (np.asarray(valid, np.float32).reshape(size) > 0).astype(np.float32)
    return np.concatenate([np.moveaxis(_pu(history, scale), 2, 0) * keep, keep[None]], 0).astype(np.float32)


# ---- OIDN's UNet ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Layout:
    """The layer names of one UNet layout: ``stages[k]`` are the convolutions at resolution level k
    before the k-th 2×2 pooling (levels 0–3), then the bottleneck (level 4), the decoder's levels
    (two convolutions each, skips ``pool3`` … ``pool1`` and the input ``x``) and the output conv."""
    stages: tuple[tuple[str, ...], ...]
    bottleneck: tuple[str, ...] = ("enc_conv5a", "enc_conv5b")
    levels: tuple[tuple[str, str, str], ...] = (("dec_conv4a", "dec_conv4b", "pool3"),
                                                ("dec_conv3a", "dec_conv3b", "pool2"),
                                                ("dec_conv2a", "dec_conv2b", "pool1"),
                                                ("dec_conv1a", "dec_conv1b", "x"))
    output: str = "dec_conv0"

    @property
    def encoder(self) -> tuple[str, ...]:
        return tuple(n for stage in self.stages for n in stage) + self.bottleneck

    @property
    def decoder(self) -> tuple[str, ...]:
        return tuple(n for a, b, _ in self.levels for n in (a, b)) + (self.output,)

    @property
    def layers(self) -> tuple[str, ...]:
        return self.encoder + self.decoder

    @property
    def level(self) -> dict[str, int]:
        """The resolution each layer works at: 0 the full image, k after k 2×2 poolings (4: the bottleneck)."""
        out = {n: k for k, stage in enumerate(self.stages) for n in stage}
        out.update({n: 4 for n in self.bottleneck})
        out.update({n: 3 - k for k, (a, b, _) in enumerate(self.levels) for n in (a, b)})
        return {**out, self.output: 0}

    @property
    def first(self) -> str:
        return self.stages[0][0]


UNET = Layout(stages=(("enc_conv0", "enc_conv1"), ("enc_conv2",), ("enc_conv3",), ("enc_conv4",)))
UNET_LARGE = Layout(stages=(("enc_conv1a", "enc_conv1b"), ("enc_conv2a", "enc_conv2b"), ("enc_conv3a", "enc_conv3b"),
                            ("enc_conv4a", "enc_conv4b")), output="dec_conv1c")
LAYOUTS = (UNET, UNET_LARGE)
# OIDN's (regular) UNet, the layout every network but the _large ones has
ENCODER, DECODER, LAYERS, LEVEL = UNET.encoder, UNET.decoder, UNET.layers, UNET.level


def layout_of(names) -> Layout:
    """The layout whose layers are all in ``names`` (a TZA archive's tensor names or a widths dict)."""
    names = {n.split(".")[0] for n in names}
    for layout in LAYOUTS:
        if set(layout.layers) <= names:
            return layout
    raise WeightsError("not an OIDN UNet: the layers of neither OIDN's UNet nor its UNetLarge "
                       f"(e.g. no {UNET.first} or {UNET_LARGE.first})")


def encode(layout: Layout, conv, x: torch.Tensor) -> dict[str, torch.Tensor]:
    """The encoder's features for the decoder: ``x`` (the input), ``full`` (level 0 before pooling),
    ``pool1`` … ``pool3``, ``bottleneck``; ``conv(name, h)`` runs one layer and its ReLU (the base's own,
    or the Control Module's copy with its timestep bias)."""
    feats, h = {"x": x}, x
    for k, stage in enumerate(layout.stages):
        for name in stage:
            h = conv(name, h)
        if k == 0:
            feats["full"] = h
        h = F.max_pool2d(h, 2)
        if k < 3:
            feats[f"pool{k + 1}"] = h
    for name in layout.bottleneck:
        h = conv(name, h)
    feats["bottleneck"] = h
    return feats


class UNet(nn.Module):
    """OIDN's UNet with the layer names of its weights; ``widths`` maps a layer to (out, in) channels and
    says the layout (``layout_of``)."""

    def __init__(self, widths: dict[str, tuple[int, int]]):
        super().__init__()
        self.layout = layout_of(widths)
        self.widths = {n: tuple(widths[n]) for n in self.layout.layers}
        for name in self.layout.layers:
            out_c, in_c = self.widths[name]
            setattr(self, name, nn.Conv2d(in_c, out_c, 3, padding=1))
        self.in_channels = self.widths[self.layout.first][1]

    @classmethod
    def from_tza(cls, tensors: dict[str, TZATensor]) -> "UNet":
        """The network with the archive's weights (float16 in the file, float32 here)."""
        layout = layout_of(tensors)
        widths = {}
        for name in layout.layers:
            w = tensors.get(f"{name}.weight")
            if w is None or w.array.ndim != 4:
                raise WeightsError(f"TZA has no 4-d {name}.weight: not an OIDN UNet")
            widths[name] = (int(w.array.shape[0]), int(w.array.shape[1]))
        net = cls(widths)
        state = {f"{n}.{p}": torch.from_numpy(tensors[f"{n}.{p}"].array.astype(np.float32)) for n in layout.layers
                 for p in ("weight", "bias")}
        net.load_state_dict(state)
        return net

    def to_tza(self) -> dict[str, TZATensor]:
        """The weights as OIDN reads them: float16, ``oihw`` weights and ``x`` biases, in OIDN's order."""
        out = {}
        for name in self.layout.layers:
            conv = getattr(self, name)
            out[f"{name}.weight"] = TZATensor(conv.weight.detach().cpu().to(torch.float16).numpy(), "oihw")
            out[f"{name}.bias"] = TZATensor(conv.bias.detach().cpu().to(torch.float16).numpy(), "x")
        return out

    def encode(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """The features the decoder reads: ``x`` (the input), ``pool1``..``pool3``, ``bottleneck``."""
        feats = encode(self.layout, lambda name, h: F.relu(getattr(self, name)(h)), x)
        del feats["full"]
        return feats

    def decode(self, feats: dict[str, torch.Tensor], residuals: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        """The output from ``encode``'s features; ``residuals`` (same names and shapes) are added to
        the skips and the bottleneck first (the Control Module's way in)."""
        r = residuals or {}

        def feat(name: str) -> torch.Tensor:
            return feats[name] + r[name] if name in r else feats[name]

        h = feat("bottleneck")
        for a, b, skip in self.layout.levels:
            h = torch.cat([F.interpolate(h, scale_factor=2.0, mode="nearest"), feat(skip)], 1)
            h = F.relu(getattr(self, b)(F.relu(getattr(self, a)(h))))
        return getattr(self, self.layout.output)(h)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(x))


def load_unet(name: str, tza_file: str | None = None) -> UNet:
    """OIDN's network ``name`` (``train.oidn``'s weights): from ``tza_file``, else from pyoidn's library."""
    source = str(tza_file) if tza_file else f"{oidn.library_path()}:{name}"
    return UNet.from_tza(read_tza(oidn.weights_blob(name, tza_file), source))


@torch.no_grad()
def unet_denoise(net: UNet, color: np.ndarray, albedo: np.ndarray | None = None, normal: np.ndarray | None = None,
            device: str | torch.device = "cpu") -> np.ndarray:
    """(H, W, 3) float32 HDR: what OIDN's filter returns for these images with ``net``'s weights
    (HDR mode, autoexposure, aux not prefiltered). Albedo/normal are used only if ``net`` reads them."""
    aux = [albedo, normal][: (net.in_channels - 3) // 3]
    if any(a is None for a in aux):
        raise WeightsError(f"this OIDN network reads {net.in_channels} channels: it needs "
                           f"{'albedo and normal' if net.in_channels == 9 else 'albedo'}")
    scale = autoexposure(color)
    x = network_input(color, *aux, scale=scale).to(device)
    net = net.to(device).eval()
    out = network_output(net(x), scale, color.shape[:2])
    return out[0].permute(1, 2, 0).float().cpu().numpy()


# ---- the Control Module ---------------------------------------------------------------------------


def skip_sources(layout: Layout) -> dict[str, str]:
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

    def __init__(self, base: UNet, extra: int):
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
        feats = encode(self.layout, lambda name, h: self._conv(name, h, emb), x)
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

    multiple = ALIGNMENT

    def __init__(self, base: UNet, cond_channels: int, control: bool = True, history: bool = False):
        """``history``: the condition is ``cond_names(True)`` (the model reads the past)."""
        super().__init__()
        self.base = base.requires_grad_(False).eval()
        self.cond_channels, self.history = int(cond_channels), bool(history)
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


def clean_aux(meta: dict) -> bool:
    """Whether a model (its model.json) feeds its base prefiltered albedo and normal."""
    return oidn.clean_aux(meta.get("base_network", NETWORK))


# ---- where models are --------------------------------------------------------------------------


def run_dir(cfg: Config, spp: int | str, variant: str | None = None) -> Path:
    """``diffusion_spp4``, ``diffusion_sppany``, ``diffusion_sppany_<variant>`` under ``cfg.runs``
    (``pipeline.config.run_dir``)."""
    return config_mod.run_dir(cfg, "diffusion", spp, variant)


def oidn_ft_blob(folder: Path, network: str) -> Path:
    """Where a model folder (``train/shipped``, an export) keeps OIDN's ``network`` fine-tuned, the weights
    it runs on inputs without the layers its base reads; the folder may not have them."""
    return Path(folder) / "oidn_ft" / f"{network}.tza"


def find_run(cfg: Config, spp: int | str, variant: str | None = None) -> Path:
    """The trained run for ``spp``: ``diffusion_spp<N>[_variant]`` if it exists, else the spp-conditioned
    ``diffusion_sppany[_variant]`` (one model serves every sample count), else (no variant, and
    ``diffusion.shipped``) the model shipped with the repository (``SHIPPED_MODEL``); CheckpointError (a StoreError)
    if none. A run trained on another store than the config's (its model.json's ``store``) is passed over, said in
    one line: another config's run in a shared folder is not this config's model. ``diffusion.model``, where set,
    is the model of the lookup without a variant, whatever the runs folder holds."""
    if variant is None and cfg.diffusion.model:
        folder = Path(cfg.diffusion.model)
        if not (folder / "model.json").is_file():
            raise CheckpointError(f"diffusion.model: {folder} has no model.json (expected a run folder or an "
                                  "exported model such as train/shipped)")
        return folder
    named = variant if variant is not None else cfg.diffusion.name
    shipped = SHIPPED_MODEL if not named and cfg.diffusion.shipped else None
    folder = config_mod.find_run(cfg, "diffusion", spp, "model.json", variant)
    if folder is not None and not trained_on(folder, cfg.store):
        instead = f"using {shipped}" if shipped is not None else "no other model"
        _note_once(f"note: {folder} was trained on {trained_store(folder)}, not this config's store {cfg.store}: "
                   f"{instead}")
        folder = None
    if folder is None and shipped is not None:
        return shipped
    if folder is not None:
        return folder
    candidates = config_mod.run_candidates(cfg, "diffusion", spp, variant) + ([shipped] if shipped else [])
    raise CheckpointError(f"no diffusion checkpoint in {' or '.join(map(str, candidates))} trained on {cfg.store}: run "
                          f"`make train SPP={spp}` or `make train SPP=any`" +
                          (f" with diffusion.name={variant}" if variant else ""))


def trained_on(folder: Path, store: str) -> bool:
    """Whether the run in ``folder`` was trained on ``store`` (the same folder; a record without a store: yes)."""
    recorded = trained_store(folder)
    return recorded is None or Path(recorded).resolve() == Path(store).resolve()


def trained_store(folder: Path) -> str | None:
    """The store a run's model.json says it was trained on (None where it says none); loading checks the rest."""
    record = read_json(Path(folder) / "model.json", "model record")
    return record.get("store") if isinstance(record, dict) else None


_NOTED: set[str] = set()


def _note_once(line: str) -> None:
    """Print ``line`` the first time it comes (the evaluator looks a run up once per sample count)."""
    if line not in _NOTED:
        _NOTED.add(line)
        print(line, flush=True)


# ---- saving and loading ------------------------------------------------------------------------


def save(folder: Path, model: ControlledOIDN, blob: bytes, what: str, network: str, form, spps: list[int],
         record: dict) -> None:
    """The Control Module, the base's blob and model.json (``form``: the ``Formulation`` it was trained with)."""
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "base.tza").exists() or (folder / "base.tza").read_bytes() != blob:
        atomic_write_bytes(folder / "base.tza", lambda tmp: Path(tmp).write_bytes(blob))
    weights.save(folder, "oidn_control", model.control.state_dict(), {
        "base": "base.tza", "base_network": network, "base_what": what, "base_sha256": hashlib.sha256(blob).hexdigest(),
        "cond_channels": cond_names(model.history), "spp": spps,
        "formulation": form.record(), **record}, weights="control.safetensors")


def load(folder: str | Path, device="cpu") -> tuple[ControlledOIDN, dict]:
    """(the controlled model in eval mode, model.json) of a run or an exported model folder."""
    folder = Path(folder)
    meta = weights.read_record(folder, "oidn_control", "run `make train SPP=any`")
    blob = (folder / meta["base"]).read_bytes()
    weights.check_sha256(blob, meta["base_sha256"], f"{folder / meta['base']}: the base", "restore it or retrain")
    history = reads_history(meta["cond_channels"])
    if meta["cond_channels"] != cond_names(history):
        raise CheckpointError(f"{folder / 'model.json'}: trained on another condition layout "
                              f"({len(meta['cond_channels'])} channels, this code makes {len(cond_names(history))}); "
                              "retrain")
    model = ControlledOIDN(UNet.from_tza(read_tza(blob, str(folder / meta["base"]))), len(cond_names(history)),
                           history=history)
    model.control.load_state_dict({k: v.float() for k, v in weights.load_tensors(folder / "control.safetensors").items()})
    return model.to(device).eval(), meta


def reads_history(cond_channels: list[str]) -> bool:
    """Whether a model reads the past: its condition (model.json's ``cond_channels``) has the history channels."""
    return HISTORY_CHANNELS[0] in cond_channels


def cond_layout(width: int) -> list[str]:
    """The condition channels of a condition ``width`` channels wide (a pack's ``cond``): with or without the
    history; ValueError for any other width."""
    for history in (False, True):
        if len(cond_names(history)) == width:
            return cond_names(history)
    raise ValueError(f"a condition of {width} channels: expected {len(cond_names())} or {len(cond_names(True))}")


def widen_control(state: dict[str, torch.Tensor], layout: Layout, x_channels: int, old: list[str], new: list[str]
                  ) -> dict[str, torch.Tensor]:
    """A Control Module's weights trained on the condition ``old`` (channel names) for the condition ``new`` (a
    superset): its first convolution's column of each input channel moved to where ``new`` puts it, the new
    channels' columns zero, so the module's output is what it was whatever the new channels hold (a warm start
    that begins at the model it starts from). The first convolution reads x ⊕ cond ⊕ z_t."""
    gone = [n for n in old if n not in new]
    if gone:
        raise CheckpointError(f"the new condition lacks channels the model reads: {', '.join(gone[:4])}")
    key = f"encoder.{layout.first}.weight"
    w = state[key]
    z = w.shape[1] - x_channels - len(old)
    cols = lambda names: [f"x.{i}" for i in range(x_channels)] + list(names) + [f"z.{i}" for i in range(z)]  # noqa: E731
    before, after = cols(old), cols(new)
    wide = w.new_zeros(w.shape[0], len(after), *w.shape[2:])
    for j, name in enumerate(after):
        if name in before:
            wide[:, j] = w[:, before.index(name)]
    return {**state, key: wide}
