"""AFGSA: Monte Carlo denoising via auxiliary feature guided self-attention (Yu et al. 2021, ACM TOG
40(6)), the third competitor of the paper's Table 1, after the paper and its authors' public code:
the network, its patch critic, their losses, the training recipe and the checkpoint loader.

    afgsa.train(cfg, spp=4)     → runs/<...>/afgsa_spp4/   (afgsa.target=gt1: afgsa_gt1_spp4/;
                                  spp="any": afgsa_sppany/, crops drawn at 4, 8, ... 64 spp)
    afgsa.load_model(folder)    → (AFGSANet, its model.json)

    noisy radiance (log) ──► multi-scale extractor (1×1, 3×3, 5×5 convs) ──► x ─┐
    auxiliary buffers    ──► multi-scale extractor ─────────────────────────► a ─┤
                                                                                  ▼
    N transformer blocks:   x ← x + GuidedAttention(x, a);   x ← x + FFN(x)       (a is not updated)
    reconstruction head:    log-radiance = log1p(noisy colour) + head(x)

**Guided attention** (``GuidedAttention``): the guide g = ReLU(W [x; a]) fuses the noisy and the
auxiliary features; queries and keys come from g, values from x alone. Which pixels a pixel
averages is decided by geometry and materials as well as by the noisy colour, but what it
averages is the noisy signal: self-attention as a non-local means filter in an embedding space
that the auxiliary buffers shape.

**Block-wise attention** (``window_attention``): the image is cut into block×block query blocks;
each block attends to its (block + 2·halo)² neighbourhood (HaloNet-style), so the cost is
O(H·W·(block + 2·halo)²), linear in the pixel count. Keys outside the image (borders, and the
padding to a multiple of the block size) are masked out, never zero-padded, so any image size
works and a single block covering the whole image is exactly full self-attention. Learned
row/column embeddings of the key's position in the neighbourhood are added to the keys (the
authors' choice).

Inputs are the project's encoding (``clean.data.frame_inputs``): the radiance buffers
(colour and its exact decomposition, log1p) and their relative-variance features feed the noisy
extractor; albedo, normal, depth, roughness, metallic, transmission and their variance features
feed the auxiliary one (``branch_channels``). The network predicts a log-space residual of the
noisy colour; ``forward`` returns HDR radiance (``expm1``, clamped to [0, ``LOG_MAX``] in log
space, so finite for every finite input, and to at most twice the brightest noisy pixel nearby
plus 1, ``BOUND_RADIUS``), with the Isik network's signature
``forward(inputs, radiance)``, so ``clean.apply.denoise`` (tiling) and the evaluator run both.

Sizes (``afgsa`` config section), ours vs the paper's: 32 vs 256 transformer channels, 32 vs 256
channels per extractor branch, 2 vs 5 transformer blocks, 2 vs 4 heads; block 8 and halo 3 as the
paper. ``PatchCritic`` is the adversarial loss's discriminator: a small fully convolutional patch
critic (the paper uses a VGG-style critic on 128² crops; the WGAN-GP formulation is the same).

**Training** (``afgsa_recipe``, run by ``clean.train``'s loop: crops, validation, checkpoints, exact
resume): the generator G learns with L1 in log1p space plus a WGAN-GP adversarial term (the
authors' code: weight 5e-3, gradient penalty 10), the critic D with the WGAN-GP loss:

    L_D = E[D(G(x))] − E[D(y)] + λ_gp E[(‖∇D(x̂)‖₂ − 1)²],   x̂ = α y + (1 − α) G(x), α ~ U(0, 1)
    L_G = ‖G(x) − y‖₁ + w_adv (−E[D(G(x))])

with y the target (``afgsa.target``: GT_clean, or GT1 for the experiment of ``train.baselines.afgsa_report``)
in log1p space; per batch one critic step, then one generator step (Adam, as the paper).
w_adv = 0 is the L1-only ablation: the critic is not used.
"""
from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from mcdenoise.clean.data import CHANNELS, IN_CHANNELS, INPUT_CLAMP, RADIANCE
from mcdenoise.clean.fit import apply_update
from mcdenoise.clean.model import load_model as load_network
from mcdenoise.clean.train import Recipe, train_recipe
from mcdenoise.pipeline import config as config_mod, schema
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.errors import TrainError

# Output clamp in log1p space: expm1(25) ≈ 7e10 is far above any radiance we render (1e5 in the
# stability suite) and keeps the HDR output finite whatever the weights predict.
LOG_MAX = 25.0
# Inference bound: a pixel's output is at most 2·m + 1, m the brightest noisy pixel within this
# radius (log1p(2m + 1) = log1p(m) + log 2). A denoiser averages; an untrained or out-of-range
# network otherwise extrapolates in log space (1e5 everywhere came out as 3e6). The radius stays
# inside clean.apply's tile margin, so tiling does not change the bound.
BOUND_RADIUS = 8


def branch_channels() -> tuple[list[int], list[int], slice]:
    """(noisy channels, auxiliary channels, colour's log channels) as indices into ``frame_inputs``.

    Radiance buffers and their variance features are the noisy signal; every other buffer (and its
    variance feature) is an auxiliary feature."""
    radiance = {b.name for b in schema.BUFFERS if b.radiance}
    noisy, aux, start, colour = [], [], 0, None
    for key, n, _ in CHANNELS:
        idx = list(range(start, start + n))
        (noisy if key.removesuffix(".variance") in radiance else aux).extend(idx)
        if key == RADIANCE:
            colour = slice(start, start + n)
        start += n
    return noisy, aux, colour


# ---- block-wise attention ------------------------------------------------------------------


def _blocks(x: torch.Tensor, block: int) -> torch.Tensor:
    """(B, C, H, W) with H, W multiples of ``block`` → (B·nb, block², C), blocks in raster order."""
    B, C, H, W = x.shape
    x = x.reshape(B, C, H // block, block, W // block, block).permute(0, 2, 4, 3, 5, 1)
    return x.reshape(-1, block * block, C)


def _neighbourhoods(x: torch.Tensor, block: int, halo: int) -> torch.Tensor:
    """(B, C, H, W) → (B·nb, win², C): the (block + 2·halo)² window around each block (zeros outside)."""
    C = x.shape[1]
    win = block + 2 * halo
    cols = F.unfold(x, kernel_size=win, stride=block, padding=halo)          # (B, C·win², nb)
    return cols.reshape(x.shape[0], C, win * win, -1).permute(0, 3, 2, 1).reshape(-1, win * win, C)


def window_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, heads: int, block: int, halo: int,
                     key_position: torch.Tensor | None = None) -> torch.Tensor:
    """Multi-head attention of every pixel over the (block + 2·halo)² neighbourhood of its block.

    q, k, v: (B, C, H, W), any H, W (padded internally to multiples of ``block``; padded and
    out-of-image keys are masked). ``key_position``: optional (win, win, C // heads) added to every
    head's keys by their position in the neighbourhood. Returns (B, C, H, W):

        out_p = Σ_q softmax_q(⟨q_p, k_q⟩ / √d) v_q   per head, q over p's block neighbourhood.
    """
    B, C, H, W = q.shape
    if C % heads:
        raise ValueError(f"{C} channels do not split into {heads} heads")
    d = C // heads
    ph, pw = (-H) % block, (-W) % block
    valid = torch.ones(B, 1, H, W, dtype=q.dtype, device=q.device)
    if ph or pw:
        q, k, v, valid = (F.pad(t, (0, pw, 0, ph)) for t in (q, k, v, valid))
    Hp, Wp = H + ph, W + pw
    win = block + 2 * halo
    qb = _blocks(q, block)                                                  # (N, block², C)
    kb, vb = _neighbourhoods(k, block, halo), _neighbourhoods(v, block, halo)   # (N, win², C)
    mask = _neighbourhoods(valid, block, halo)[..., 0] > 0.5                 # (N, win²)

    def split(t):                                                           # (N, n, C) → (N, heads, n, d)
        return t.reshape(t.shape[0], t.shape[1], heads, d).transpose(1, 2)

    qh, kh, vh = split(qb), split(kb), split(vb)
    if key_position is not None:
        kh = kh + key_position.reshape(1, 1, win * win, d)
    # Every query block lies inside its own window and holds at least one real pixel, so no row of
    # the mask is all False: the softmax is always over at least one key.
    out = F.scaled_dot_product_attention(qh, kh, vh, attn_mask=mask[:, None, None, :])
    out = out.transpose(1, 2).reshape(B, Hp // block, Wp // block, block, block, C)
    out = out.permute(0, 5, 1, 3, 2, 4).reshape(B, C, Hp, Wp)
    return out[..., :H, :W]


class GuidedAttention(nn.Module):
    """Auxiliary-feature-guided self-attention: queries and keys from the guide g = ReLU(W [x; a]),
    values from the noisy features x. ``attend(x, guide)`` is the attention given a guide (with
    ``guide = x`` it is plain self-attention of x)."""

    def __init__(self, channels: int, heads: int, block: int, halo: int):
        super().__init__()
        d = channels // heads
        if channels % heads or d % 2:
            raise ValueError(f"channels {channels} must split into {heads} heads of an even size")
        self.heads, self.block, self.halo = int(heads), int(block), int(halo)
        self.fuse = nn.Sequential(nn.Conv2d(2 * channels, channels, 1), nn.ReLU())
        self.q, self.k, self.v = (nn.Conv2d(channels, channels, 1, bias=False) for _ in range(3))
        win = self.block + 2 * self.halo
        # Row and column embeddings, half of each head's channels each (the authors' layout).
        self.pos_row = nn.Parameter(0.1 * torch.randn(win, 1, d // 2))
        self.pos_col = nn.Parameter(0.1 * torch.randn(1, win, d // 2))

    def key_position(self) -> torch.Tensor:
        win = self.block + 2 * self.halo
        return torch.cat([self.pos_row.expand(win, win, -1), self.pos_col.expand(win, win, -1)], dim=-1)

    def attend(self, x: torch.Tensor, guide: torch.Tensor) -> torch.Tensor:
        return window_attention(self.q(guide), self.k(guide), self.v(x), self.heads, self.block, self.halo,
                                self.key_position())

    def forward(self, x: torch.Tensor, aux: torch.Tensor) -> torch.Tensor:
        return self.attend(x, self.fuse(torch.cat([x, aux], dim=1)))


class TransformerBlock(nn.Module):
    """x ← x + GuidedAttention(x, a); x ← x + FFN(x), FFN = two 3×3 conv + ReLU (the paper's)."""

    def __init__(self, channels: int, heads: int, block: int, halo: int):
        super().__init__()
        self.attention = GuidedAttention(channels, heads, block, halo)
        self.ffn = nn.Sequential(_conv(channels, channels, 3), nn.ReLU(), _conv(channels, channels, 3), nn.ReLU())

    def forward(self, x: torch.Tensor, aux: torch.Tensor) -> torch.Tensor:
        x = x + self.attention(x, aux)
        return x + self.ffn(x)


def _conv(cin: int, cout: int, size: int) -> nn.Conv2d:
    # Replicate padding: reflect needs the image wider than the padding (an 8×8 frame is not).
    return nn.Conv2d(cin, cout, size, padding=size // 2, padding_mode="replicate")


class MultiScale(nn.Module):
    """act(1×1 ‖ 3×3 ‖ 5×5 convs of the input) → 1×1 conv → act: the paper's feature extractor."""

    def __init__(self, cin: int, width: int, cout: int):
        super().__init__()
        self.branches = nn.ModuleList(_conv(cin, width, s) for s in (1, 3, 5))
        self.merge = nn.Conv2d(3 * width, cout, 1)
        self.act = nn.LeakyReLU(0.2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.merge(self.act(torch.cat([b(x) for b in self.branches], dim=1))))


class AFGSANet(nn.Module):
    """forward(inputs (B, C, H, W) of ``frame_inputs``, radiance (B, 3, H, W)) → HDR radiance (B, 3, H, W)."""

    def __init__(self, in_channels: int, channels: int = 32, extractor_channels: int = 32, blocks: int = 2,
                 heads: int = 2, block_size: int = 8, halo: int = 3):
        super().__init__()
        self.noisy_idx, self.aux_idx, self.colour = branch_channels()
        if int(in_channels) != len(self.noisy_idx) + len(self.aux_idx):
            raise ValueError(f"in_channels {in_channels} is not the {len(self.noisy_idx) + len(self.aux_idx)} "
                             "channels of clean.data.frame_inputs")
        self.hparams = {"in_channels": int(in_channels), "channels": int(channels),
                        "extractor_channels": int(extractor_channels), "blocks": int(blocks), "heads": int(heads),
                        "block_size": int(block_size), "halo": int(halo)}
        self.noisy = MultiScale(len(self.noisy_idx), extractor_channels, channels)
        self.aux = nn.Sequential(MultiScale(len(self.aux_idx), extractor_channels, channels),
                                 nn.Conv2d(channels, channels, 1), nn.LeakyReLU(0.2))
        self.blocks = nn.ModuleList(TransformerBlock(channels, heads, block_size, halo) for _ in range(int(blocks)))
        self.head = nn.Sequential(_conv(channels, channels, 3), nn.ReLU(), _conv(channels, channels, 3), nn.ReLU(),
                                  _conv(channels, 3, 3))

    def log_forward(self, inputs: torch.Tensor) -> torch.Tensor:
        """log1p-space radiance (B, 3, H, W), unclamped: what the L1 and adversarial losses see."""
        x = inputs.clamp(-INPUT_CLAMP, INPUT_CLAMP)
        feat, aux = self.noisy(x[:, self.noisy_idx]), self.aux(x[:, self.aux_idx])
        for block in self.blocks:
            feat = block(feat, aux)
        return x[:, self.colour].clamp(min=0.0) + self.head(feat)

    def forward(self, inputs: torch.Tensor, radiance: torch.Tensor) -> torch.Tensor:
        if inputs.shape[-2:] != radiance.shape[-2:]:
            raise ValueError(f"inputs {tuple(inputs.shape)} and radiance {tuple(radiance.shape)} differ in size")
        return torch.expm1(torch.minimum(self.log_forward(inputs), self.log_bound(inputs)).clamp(0.0, LOG_MAX))

    def log_bound(self, inputs: torch.Tensor) -> torch.Tensor:
        """log1p(2·m + 1) per pixel, m the brightest noisy colour within ``BOUND_RADIUS`` (see there)."""
        colour = inputs[:, self.colour].clamp(0.0, INPUT_CLAMP)
        local = F.max_pool2d(colour, 2 * BOUND_RADIUS + 1, stride=1, padding=BOUND_RADIUS)
        return local + math.log(2.0)


class PatchCritic(nn.Module):
    """WGAN critic on log-radiance crops: 3×3 conv, then ``levels`` stride-2 4×4 convs doubling the
    channels, then a 3×3 conv to one score per patch. ``forward`` → (B,) mean patch score."""

    def __init__(self, channels: int = 16, levels: int = 3):
        super().__init__()
        self.hparams = {"channels": int(channels), "levels": int(levels)}
        layers, c = [nn.Conv2d(3, channels, 3, padding=1), nn.LeakyReLU(0.2)], channels
        for _ in range(int(levels)):
            layers += [nn.Conv2d(c, 2 * c, 4, stride=2, padding=1), nn.LeakyReLU(0.2)]
            c *= 2
        layers.append(nn.Conv2d(c, 1, 3, padding=1))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x).mean(dim=(1, 2, 3))


# ---- losses --------------------------------------------------------------------------------


def log_radiance(hdr: torch.Tensor) -> torch.Tensor:
    """HDR radiance → the log1p space AFGSA predicts and is trained in (negatives clamped to 0)."""
    return torch.log1p(hdr.clamp(min=0.0))


def gradient_penalty(critic, real: torch.Tensor, fake: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """E[(‖∇D(x̂)‖₂ − 1)²] at random points x̂ between real and fake (one α per crop)."""
    alpha = torch.rand(real.shape[0], 1, 1, 1, generator=generator).to(real)
    mixed = (alpha * real + (1 - alpha) * fake).requires_grad_(True)
    grad, = torch.autograd.grad(critic(mixed).sum(), mixed, create_graph=True)
    return ((grad.flatten(1).norm(dim=1) - 1.0) ** 2).mean()


def critic_loss(critic, real: torch.Tensor, fake: torch.Tensor, gp_weight: float,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """WGAN-GP loss of the critic (``fake`` is detached here); terms: the Wasserstein estimate
    E[D(y)] − E[D(G(x))] and the penalty."""
    fake = fake.detach()
    wasserstein = critic(real).mean() - critic(fake).mean()
    gp = gradient_penalty(critic, real, fake, generator)
    loss = -wasserstein + gp_weight * gp
    return loss, {"wasserstein": float(wasserstein.detach()), "gp": float(gp.detach())}


def generator_loss(fake: torch.Tensor, real: torch.Tensor, critic, adv_weight: float
                   ) -> tuple[torch.Tensor, dict[str, float]]:
    """L1 (log space) + adv_weight · (−E[D(fake)]); with adv_weight 0 the critic is never called."""
    rec = (fake - real).abs().mean()
    if adv_weight == 0:
        return rec, {"l1": float(rec.detach())}
    adv = -critic(fake).mean()
    return rec + adv_weight * adv, {"l1": float(rec.detach()), "adv": float(adv.detach())}


# ---- training and loading --------------------------------------------------------------------


def afgsa_hparams(cfg: Config) -> dict:
    a = cfg.afgsa
    return {"in_channels": IN_CHANNELS, "channels": a.channels, "extractor_channels": a.extractor_channels,
            "blocks": a.blocks, "heads": a.heads, "block_size": a.block_size, "halo": a.halo}


def afgsa_recipe(cfg: Config, spp) -> Recipe:
    """AFGSA as a ``clean.train`` recipe: per batch one WGAN-GP critic step, then one generator step on
    L1 (log space) + adv_weight x the adversarial term (the authors' order); adv_weight 0 trains the
    generator on L1 alone and never touches the critic."""
    a = cfg.afgsa
    device = config_mod.pick_device(a.device)
    torch.manual_seed(cfg.seed)
    generator = AFGSANet(**afgsa_hparams(cfg)).to(device)
    critic = PatchCritic(a.critic_channels, a.critic_levels).to(device)
    opts = {"generator": torch.optim.Adam(generator.parameters(), lr=a.lr),
            "critic": torch.optim.Adam(critic.parameters(), lr=a.lr_critic)}
    g_params, d_params = list(generator.parameters()), list(critic.parameters())
    adversarial = a.adv_weight > 0

    def step(batch: dict, rng: torch.Generator) -> tuple[dict, bool]:
        fake, real = generator.log_forward(batch["inputs"]), log_radiance(batch["target"])
        ok, terms = True, {}
        if adversarial:
            d_loss, terms = critic_loss(critic, real, fake, a.gp_weight, rng)
            ok = apply_update(d_loss, opts["critic"], d_params, a.grad_clip)
        g_loss, g_terms = generator_loss(fake, real, critic if adversarial else None, a.adv_weight)
        ok = apply_update(g_loss, opts["generator"], g_params, a.grad_clip) and ok
        return {"loss": g_terms.pop("l1"), **g_terms, **terms}, ok

    fp = {"mode": "afgsa", "spp": spp, "seed": cfg.seed, "hparams": afgsa_hparams(cfg), "critic": critic.hparams,
          **{k: getattr(a, k) for k in ("target", "batch_size", "crop", "crops_per_frame", "lr", "lr_critic",
                                         "adv_weight", "gp_weight", "grad_clip")}}
    title = f"AFGSA, {spp} spp -> {a.target} (adv. weight {a.adv_weight:g})"
    state = torch.nn.ModuleDict({"generator": generator, "critic": critic})
    return Recipe("afgsa", spp, a, generator, state, opts, step, fp, "afgsa", title, "L1 (log1p)",
                  config_mod.run_dir(cfg, "afgsa", spp), target=a.target,
                  meta={"smape_eps": cfg.clean.smape_eps, "target": a.target, "afgsa": vars(a).copy()})


def train(cfg: Config, spp, quiet: bool = False) -> dict:
    """Train (or resume) AFGSA from the ``spp`` (or 'any': 4/16/64) low-spp buffers to ``afgsa.target``;
    a summary dict. The best weights end up in ``pipeline.config.run_dir(cfg, "afgsa", spp)``."""
    if not spp:
        raise TrainError("the afgsa model needs an spp (make train MODEL=afgsa SPP=4)")
    return train_recipe(cfg, afgsa_recipe(cfg, spp), quiet=quiet)


def load_model(path: str | Path, device: str | torch.device = "cpu") -> tuple[AFGSANet, dict]:
    """An AFGSA run's ``model.safetensors`` (the run folder or the file) and its ``model.json``."""
    return load_network(path, device, network=AFGSANet, kind="afgsa")
