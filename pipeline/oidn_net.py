"""OIDN's network in PyTorch: its UNet and its HDR input/output processing, equal to pyoidn's output.

``pipeline.oidn`` runs OIDN itself (the baseline, the first estimate); this twin is what trains.
Built from a TZA archive's shapes (``pipeline.tza``, ``pipeline.oidn_weights``), so the colour,
+albedo and +albedo+normal networks (3/6/9 input channels), their ``_small`` variants and the
``_large`` layout (``rt_hdr_calb_cnrm_large``, what OIDN runs at quality high on prefiltered aux)
all load.

The UNet (OIDN's ``training/model.py``, ``UNet`` and ``UNetLarge``; ``Layout`` names the layers):
3×3 convolutions with padding 1, each followed by a ReLU except the last; five encoder levels with
2×2 max pooling after the first four (one or two convolutions each; the large layout always two,
and wider); a decoder of nearest ×2 upsampling, concatenation ``[upsampled, skip]`` (the order
matters) and two convolutions per level, the last level concatenating the network input itself,
then the output convolution.

HDR processing (OIDN's core, ``input_process``/``output_process``/``autoexposure``):

- ``autoexposure``: 0.18 / 2^(mean log2 of the mean luminance of ~16×16 bins whose mean is
  above 1e-8); 1 if none is;
- input: colour × scale, NaN → 0, clamped ≥ 0, then the PU transfer normalised so that 65504 maps
  to 1 (``to_pu``); albedo NaN → 0 and clamped to [0, 1]; normal NaN → 0, clamped to [−1, 1],
  then n·0.5 + 0.5; channels in that order; zero padding at the bottom and right to a multiple of
  16;
- output: NaN → 0, clamped ≥ 0, the inverse PU transfer (``from_pu``), divided by the scale.

The network's output space (PU of the exposed radiance) is where OIDN's training kit puts its
loss, and where ``oidn_ft`` (``train.oidn_ft``) puts ours.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from . import tza
from .errors import WeightsError

ALIGNMENT = 16            # input sides are padded to a multiple of this (four 2×2 poolings)
HDR_MAX = 65504.0         # float16's largest value: PU(HDR_MAX) is normalised to 1

# PU2 fit normalised at 100 cd/m² (Aydin et al. 2008), OIDN's core/color.h.
PU_A, PU_B, PU_C, PU_D = 1.41283765e+03, 1.64593172e+00, 4.31384981e-01, -2.94139609e-03
PU_E, PU_F, PU_G = 1.92653254e-01, 6.26026094e-03, 9.98620152e-01
PU_Y0, PU_Y1 = 1.57945760e-06, 3.22087631e-02
PU_X0, PU_X1 = 2.23151711e-03, 3.70974749e-01

LUMINANCE = (0.212671, 0.715160, 0.072169)
AUTOEXPOSURE_BIN, AUTOEXPOSURE_KEY, AUTOEXPOSURE_EPS = 16, 0.18, 1e-8


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


def _pu(y: torch.Tensor) -> torch.Tensor:
    return torch.where(y <= PU_Y0, PU_A * y,
                       torch.where(y <= PU_Y1, PU_B * y.clamp(min=PU_Y0) ** PU_C + PU_D,
                                   PU_E * torch.log(y.clamp(min=PU_Y1) + PU_F) + PU_G))


def _pu_inverse(x: torch.Tensor) -> torch.Tensor:
    return torch.where(x <= PU_X0, x / PU_A,
                       torch.where(x <= PU_X1, ((x.clamp(min=PU_X0) - PU_D) / PU_B) ** (1.0 / PU_C),
                                   torch.exp((x.clamp(min=PU_X1) - PU_G) / PU_E) - PU_F))


PU_NORM = 1.0 / float(_pu(torch.tensor(HDR_MAX, dtype=torch.float64)))


def to_pu(y: torch.Tensor) -> torch.Tensor:
    """OIDN's HDR transfer: PU(y) / PU(65504), for exposed radiance y ≥ 0 (0 → 0, 65504 → 1)."""
    return _pu(y) * PU_NORM


def from_pu(x: torch.Tensor) -> torch.Tensor:
    """The inverse of ``to_pu`` (for x ≥ 0)."""
    return _pu_inverse(x / PU_NORM)


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
    def from_tza(cls, tensors: dict[str, tza.Tensor]) -> "UNet":
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

    def to_tza(self) -> dict[str, tza.Tensor]:
        """The weights as OIDN reads them: float16, ``oihw`` weights and ``x`` biases, in OIDN's order."""
        out = {}
        for name in self.layout.layers:
            conv = getattr(self, name)
            out[f"{name}.weight"] = tza.Tensor(conv.weight.detach().cpu().to(torch.float16).numpy(), "oihw")
            out[f"{name}.bias"] = tza.Tensor(conv.bias.detach().cpu().to(torch.float16).numpy(), "x")
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
    """OIDN's network ``name`` (``pipeline.oidn_weights``): from ``tza_file``, else from pyoidn's library."""
    from . import oidn_weights
    source = str(tza_file) if tza_file else f"{oidn_weights.library_path()}:{name}"
    return UNet.from_tza(tza.read(oidn_weights.load(name, tza_file), source))


@torch.no_grad()
def denoise(net: UNet, color: np.ndarray, albedo: np.ndarray | None = None, normal: np.ndarray | None = None,
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
def prefilter(net: UNet, image: torch.Tensor, kind: str) -> torch.Tensor:
    """An aux image (B, 3, H, W) on any device, denoised by OIDN's aux network ``net`` for ``kind``
    ('albedo' in [0, 1], 'normal' in [−1, 1]; NaN as 0) as OIDN's filter does; same shape and range."""
    H, W = image.shape[-2:]
    image = torch.nan_to_num(image.float(), nan=0.0)
    x = srgb(image.clamp(0.0, 1.0)) if kind == "albedo" else image.clamp(-1.0, 1.0) * 0.5 + 0.5
    y = net(F.pad(x, (0, -W % ALIGNMENT, 0, -H % ALIGNMENT)))[..., :H, :W].float().clamp(0.0, 1.0)
    return srgb_inverse(y) if kind == "albedo" else y * 2.0 - 1.0
