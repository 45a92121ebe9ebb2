"""The affinity denoiser of Isik et al. 2021 ("Interactive Monte Carlo denoising using affinity of
neural features"), single-frame: the GT cleaner of the paper's section 3.1 and the Isik baseline.

    inputs (B, C, H, W)  ──► per-pixel embedding (1×1 convs) ──► U-Net ──► for each of K iterations:
                                                                       features f (F channels),
                                                                       bandwidth a >= 0,
                                                                       centre weight c > 0
    radiance (B, 3, H, W) ──► K dilated size×size kernels, iteration k:
         out_p = Σ_q w_pq r_q / Σ_q w_pq,   w_pq = exp(−a_p ‖f_p − f_q‖² − b_p d²_pq) (q ≠ p),   w_pp = c_p

d²_pq (optional, ``variance_channel``; on in the default config) is the variance-normalized
NL-means distance of Rousselle et al. 2012 between the radiance at p and q (``range_distance``),
b_p >= 0 its learned per-pixel weight. It is our addition to Isik et al.: it is what lets the
cleaner tell 1024-spp noise from detail (see ``AffinityDenoiser``).

The kernels filter the **HDR radiance** itself: the output is a convex combination of input
radiances (weights are positive and normalized), so it stays HDR, non-negative for non-negative
input, energy is neither invented nor lost, and it is finite whenever the input radiance is
finite, whatever the network predicts. Only the network's inputs are range-compressed (by
``clean.data``; ``forward`` additionally clamps them to ±``clean.data.INPUT_CLAMP`` so that any
finite input gives finite activations).

Numerics (``apply_affinity_kernel``): the weights are computed as a softmax over the kernel's
log-weights ``−a‖f_p − f_q‖²`` and ``log c_p``. Softmax subtracts the maximum log-weight, so the
normalizer is at least 1 and never 0 even when every affinity underflows (then the result is
the centre pixel: identity); the centre weight is parametrised by its logarithm, hence strictly
positive. Neighbours outside the image get log-weight −inf (excluded), never zero padding.

Any image size works: the U-Net input is padded (replicate) to a multiple of 2^(levels−1) and the
per-pixel outputs are cropped back before filtering, so the output has the input's shape.
Memory: the kernels use shifted slices (no unfold copy); for one 256² image and a 7×7 kernel the
largest temporary is the (B, 49, H, W) log-weight stack (13 MB in float32).
"""
from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .data import INPUT_CLAMP, decode_variance

# Added to the denominator of the range distance (radiance² units): two exactly noise-free pixels
# (background, v = 0) then compare on their difference alone, far above any noise.
RANGE_EPS = 1e-10


def _offsets(size: int, dilation: int) -> list[tuple[int, int]]:
    if size % 2 != 1:
        raise ValueError(f"kernel size must be odd, got {size}")
    h = size // 2
    return [(i * dilation, j * dilation) for i in range(-h, h + 1) for j in range(-h, h + 1)]


def range_distance(radiance: torch.Tensor, variance: torch.Tensor, dy: int, dx: int, patch: int = 1) -> torch.Tensor:
    """Variance-normalized distance between each pixel p and its neighbour q = p + (dy, dx).

        d²_pq = box_patch( (mean_c (r_p − r_q)² − (v_p + min(v_p, v_q))) / (ε + v_p + v_q) ),  clamped >= 0

    The NL-means distance of Rousselle et al. 2012 ("Adaptive rendering with non-local means
    filtering"): v is the variance of the pixel estimate, so for two pixels with the same mean
    E[(r_p − r_q)²] = v_p + v_q and d² ≈ 0; the subtracted term cancels the noise's own
    contribution. ``patch`` > 0 averages the distance over a (2·patch+1)² patch (lower variance
    of the distance itself). Neighbours outside the image see the border (replicate padding);
    the caller excludes them anyway. Returns (B, 1, H, W), finite for finite inputs.
    """
    r = max(abs(dy), abs(dx))
    r_pad, v_pad = (F.pad(x, (r, r, r, r), mode="replicate") for x in (radiance, variance))
    window = _window(r, dy, dx, *radiance.shape[-2:])
    return _range_distance(radiance, variance, r_pad[window], v_pad[window], patch)


def _window(r: int, dy: int, dx: int, H: int, W: int) -> tuple:
    """Index of the neighbours q = p + (dy, dx) in a tensor padded by r on every side."""
    return (..., slice(r + dy, r + dy + H), slice(r + dx, r + dx + W))


def _range_distance(radiance, variance, rq, vq, patch: int) -> torch.Tensor:
    """``range_distance`` given the neighbours' radiance ``rq`` and variance ``vq`` (already shifted)."""
    big = torch.finfo(radiance.dtype).max
    diff = ((radiance - rq) ** 2).mean(1, keepdim=True).clamp(max=big)
    d2 = (diff - (variance + torch.minimum(variance, vq))) / (RANGE_EPS + variance + vq)
    if patch > 0:
        d2 = F.avg_pool2d(d2, 2 * patch + 1, stride=1, padding=patch, count_include_pad=False)
    return d2.clamp(min=0.0, max=big)


def affinity_weights(features: torch.Tensor, bandwidth: torch.Tensor, log_centre: torch.Tensor,
                     dilation: int = 1, size: int = 7, radiance: torch.Tensor | None = None,
                     variance: torch.Tensor | None = None, range_weight: torch.Tensor | None = None,
                     patch: int = 1) -> torch.Tensor:
    """Normalized kernel weights (B, size², H, W), one channel per offset of ``_offsets``.

        log w_pq = −a_p ‖f_p − f_q‖² − b_p d²_pq   (q ≠ p),   log w_pp = log c_p

    with the range term b_p d²_pq (``range_distance``) only where ``range_weight`` b is given
    (with the ``radiance`` and ``variance`` it measures). Neighbours outside the image get
    log-weight −inf (excluded), never zero padding.
    """
    B, _, H, W = features.shape
    offsets = _offsets(size, dilation)
    r = (size // 2) * dilation
    # a·‖Δf‖² with a = inf and ‖Δf‖² = 0 would be NaN: cap a at the largest finite value.
    big = torch.finfo(features.dtype).max
    bandwidth = bandwidth.clamp(min=0.0, max=big)
    if range_weight is not None:
        range_weight = range_weight.clamp(min=0.0, max=big)
    pad = (r, r, r, r)
    f_pad = F.pad(features, pad)
    sq = (features * features).sum(1, keepdim=True)
    sq_pad = F.pad(sq, pad)
    inside = F.pad(torch.ones(1, 1, H, W, dtype=torch.bool, device=features.device), pad)
    if range_weight is not None:
        # Padded once for all offsets (replicate: a window reads the same values at any pad width).
        r_pad, v_pad = (F.pad(x, pad, mode="replicate") for x in (radiance, variance))
    logits = []
    for dy, dx in offsets:
        if dy == 0 and dx == 0:
            logits.append(log_centre)
            continue
        window = _window(r, dy, dx, H, W)
        # ‖f_p − f_q‖² = ‖f_p‖² + ‖f_q‖² − 2 f_p·f_q: keeps only views of f_pad for backward
        # instead of one (B, F, H, W) difference per offset; clamp the round-off below 0.
        dist = (sq + sq_pad[window] - 2.0 * (features * f_pad[window]).sum(1, keepdim=True)).clamp(min=0.0)
        logit = -(bandwidth * dist)
        if range_weight is not None:
            logit = logit - range_weight * _range_distance(radiance, variance, r_pad[window], v_pad[window], patch)
        logits.append(logit.masked_fill(~inside[window], float("-inf")))
    # Softmax = max-subtracted exp / sum: the centre logit is finite, so the max is finite and
    # the normalizer >= 1; underflowing affinities just become 0 weights.
    return torch.softmax(torch.cat(logits, dim=1), dim=1)


def apply_weights(x: torch.Tensor, weights: torch.Tensor, dilation: int = 1, size: int = 7) -> torch.Tensor:
    """Σ_q w_pq x_q for x (B, C, H, W) and weights (B, size², H, W) from ``affinity_weights``."""
    H, W = x.shape[-2:]
    r = (size // 2) * dilation
    x_pad = F.pad(x, (r, r, r, r))
    out = torch.zeros_like(x)
    for k, (dy, dx) in enumerate(_offsets(size, dilation)):
        out = out + weights[:, k:k + 1] * x_pad[_window(r, dy, dx, H, W)]
    return out


def apply_affinity_kernel(radiance: torch.Tensor, features: torch.Tensor, bandwidth: torch.Tensor,
                          log_centre: torch.Tensor, dilation: int = 1, size: int = 7) -> torch.Tensor:
    """One normalized affinity filtering step (no range term).

    radiance (B, C, H, W) HDR; features (B, F, H, W); bandwidth (B, 1, H, W) >= 0 (the a_p of
    exp(−a_p ‖f_p − f_q‖²)); log_centre (B, 1, H, W), log of the centre weight c_p > 0.
    Neighbours q = p + dilation·(i, j), |i|, |j| <= size // 2, inside the image.
    Returns (B, C, H, W) = Σ_q w_pq r_q / Σ_q w_pq.
    """
    weights = affinity_weights(features, bandwidth, log_centre, dilation, size)
    return apply_weights(radiance, weights, dilation, size)


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.LeakyReLU(0.1),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.LeakyReLU(0.1))


class UNet(nn.Module):
    """Plain U-Net: two 3×3 convs per level, 2× average-pool down, nearest up + skip concat."""

    def __init__(self, cin: int, channels: list[int], cout: int):
        super().__init__()
        self.enc = nn.ModuleList()
        prev = cin
        for ch in channels:
            self.enc.append(_block(prev, ch))
            prev = ch
        self.dec = nn.ModuleList(_block(channels[i + 1] + channels[i], channels[i])
                                 for i in reversed(range(len(channels) - 1)))
        self.head = nn.Conv2d(channels[0], cout, 1)

    @property
    def multiple(self) -> int:
        return 2 ** (len(self.enc) - 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for i, block in enumerate(self.enc):
            if i:
                x = F.avg_pool2d(x, 2)
            x = block(x)
            skips.append(x)
        for block, skip in zip(self.dec, reversed(skips[:-1])):
            x = F.interpolate(x, size=skip.shape[-2:], mode="nearest")
            x = block(torch.cat([x, skip], dim=1))
        return self.head(x)


class AffinityDenoiser(nn.Module):
    """forward(inputs (B, C, H, W), radiance (B, 3, H, W) HDR) → denoised HDR radiance (B, 3, H, W).

    ``variance_channel``: index in ``inputs`` of the radiance's relative-variance feature
    (``clean.data.COLOR_VARIANCE_CHANNEL``). When given, every iteration adds the range term
    −b_p d²_pq of ``range_distance`` to its log-weights, with b_p >= 0 predicted by the U-Net like
    the bandwidth, and carries the variance through the filter (v' = Σ_q w_pq² v_q, exact for
    independent pixel noise) so that the next iteration compares on the filtered image's noise.
    Why: a 1024-spp ground truth is noisy at the 1e-3 level only, far below the feature edges the
    affinities see. Learned features alone did not find that scale within a CPU training budget
    and the cleaner converged to the identity; the variance-normalized distance tells exactly which
    neighbours differ by more than noise.
    """

    def __init__(self, in_channels: int, embed_channels: int = 32, channels: list[int] = (32, 48, 64),
                 affinity_channels: int = 8, kernel_size: int = 7, dilations: list[int] = (1, 2, 4),
                 variance_channel: int | None = None, range_patch: int = 1):
        super().__init__()
        if variance_channel is not None and not 0 <= int(variance_channel) < int(in_channels):
            raise ValueError(f"variance_channel {variance_channel} is not one of the {in_channels} input channels")
        self.hparams = {"in_channels": int(in_channels), "embed_channels": int(embed_channels),
                        "channels": [int(c) for c in channels], "affinity_channels": int(affinity_channels),
                        "kernel_size": int(kernel_size), "dilations": [int(d) for d in dilations],
                        "variance_channel": None if variance_channel is None else int(variance_channel),
                        "range_patch": int(range_patch)}
        self.kernel_size = int(kernel_size)
        self.dilations = [int(d) for d in dilations]
        self.affinity_channels = int(affinity_channels)
        self.variance_channel = self.hparams["variance_channel"]
        self.range_patch = int(range_patch)
        # Isik et al. embed each sample with a small MLP and average; we have per-pixel buffers,
        # so the embedding is a per-pixel MLP (1×1 convs).
        self.embed = nn.Sequential(nn.Conv2d(in_channels, embed_channels, 1), nn.LeakyReLU(0.1),
                                   nn.Conv2d(embed_channels, embed_channels, 1), nn.LeakyReLU(0.1))
        # features, bandwidth, log centre weight (+ range weight)
        self.per_iter = affinity_channels + 2 + (self.variance_channel is not None)
        self.unet = UNet(embed_channels, list(channels), self.per_iter * len(self.dilations))
        # Guide: the raw inputs join the learned affinity features, weighted per iteration and
        # channel by learned scales (a cross-bilateral term). Without it, training on noisy
        # inputs collapsed within one epoch to identical learned features — a uniform blur where
        # ‖f_p − f_q‖ = 0 makes the features' gradient exactly zero, so it never left.
        self.guide_scale = nn.Parameter(torch.full((len(self.dilations), int(in_channels)), 0.1))
        with torch.no_grad():
            # Start as a moderate smoother: bandwidth softplus(0.5) ≈ 1, centre weight e^0 = 1,
            # range weight softplus(0.54) = 1 (the NL-means of Rousselle et al. with k = 1).
            bias = self.unet.head.bias.view(len(self.dilations), self.per_iter)
            bias[:, affinity_channels] = 0.5
            bias[:, affinity_channels + 1] = 0.0
            if self.variance_channel is not None:
                bias[:, affinity_channels + 2] = 0.5413

    def kernel_parameters(self, inputs: torch.Tensor) -> list[tuple[torch.Tensor, ...]]:
        """Per iteration (features, bandwidth, log_centre, range_weight or None), each (B, ·, H, W)."""
        H, W = inputs.shape[-2:]
        m = self.unet.multiple
        ph, pw = (-H) % m, (-W) % m
        x = inputs.clamp(-INPUT_CLAMP, INPUT_CLAMP)
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        out = self.unet(self.embed(x))[..., :H, :W]
        guide = inputs.clamp(-INPUT_CLAMP, INPUT_CLAMP)
        params = []
        n = self.affinity_channels
        for k, chunk in enumerate(out.split(self.per_iter, dim=1)):
            feat = torch.cat([chunk[:, :n], guide * self.guide_scale[k].view(1, -1, 1, 1)], dim=1)
            rng = F.softplus(chunk[:, n + 2:n + 3]) if self.variance_channel is not None else None
            params.append((feat, F.softplus(chunk[:, n:n + 1]), chunk[:, n + 1:n + 2], rng))
        return params

    def forward(self, inputs: torch.Tensor, radiance: torch.Tensor) -> torch.Tensor:
        if inputs.shape[-2:] != radiance.shape[-2:]:
            raise ValueError(f"inputs {tuple(inputs.shape)} and radiance {tuple(radiance.shape)} differ in size")
        out = radiance
        variance = None
        if self.variance_channel is not None:
            c = self.variance_channel
            variance = decode_variance(inputs[:, c:c + 1], radiance)
        for (feat, bw, logc, rng), d in zip(self.kernel_parameters(inputs), self.dilations):
            w = affinity_weights(feat, bw, logc, d, self.kernel_size, out, variance, rng, self.range_patch)
            out = apply_weights(out, w, d, self.kernel_size)
            if variance is not None:
                variance = apply_weights(variance, w * w, d, self.kernel_size)
        return out


# ---- weights on disk: safetensors + a JSON sidecar ------------------------------------------


def load_model(path: str | Path, device: str | torch.device = "cpu",
               network: type[nn.Module] = AffinityDenoiser, kind: str = "affinity") -> tuple[nn.Module, dict]:
    """A trained run's ``model.safetensors`` and its ``model.json`` (``pipeline.weights``: a ``kind`` model;
    hparams, epoch, metrics, ...) as ``network(**hparams)``: an ``AffinityDenoiser``, or the class of
    another network that ``clean.train`` trained (a recipe's model). ``path``: the run folder or its
    ``model.safetensors``."""
    from mcdenoise.pipeline import weights
    from mcdenoise.pipeline.errors import CheckpointError

    path = Path(path)
    path = path / "model.safetensors" if path.is_dir() else path
    meta = weights.read_record(path.parent, kind, "train it first (make gt-clean, or make train MODEL=isik|afgsa)")
    try:
        model = network(**meta["hparams"])
        model.load_state_dict(weights.load_tensors(path, device))
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path}: not a usable safetensors checkpoint of this model ({first})") from None
    return model.to(device).eval(), meta
