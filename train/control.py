"""The Control Module (paper Fig. 1, after ControlNet) and the controlled denoiser around a frozen base.

The Control Module is a trainable copy of the base's input convolution, time/class/text
embeddings, down blocks and middle block. It reads the same 6-channel input as the base
(z_t ⊕ noisy radiance) plus every auxiliary buffer through a small conv stem, and returns one
residual per skip connection of the base and one for its middle block, each through a
zero-initialised 1×1 convolution:

    h_0 = conv_in(z_t ⊕ x̃) + stem(F)
    (r_1 … r_n), r_mid = zero_conv_i(encoder(h_0, emb)), zero_conv_mid(mid(…))
    ε̂ ⊕ v = base(z_t ⊕ x̃, t; skips + r_i, mid + r_mid)

At initialisation every zero conv outputs 0, so the controlled model equals the base exactly; the
stem's last layer is zero too, so the copied encoder first sees what the base's encoder sees.
Only the Control Module trains (``ControlledDenoiser.trainable_parameters``); with
``train_base=True`` the base trains as well, for comparison.

Why not ``diffusers.ControlNetModel.from_unet`` (checked with diffusers 0.42.1 on the
``default_config`` stand-in and on ``train/base_model_paper``): it cannot copy an IF-II-layout UNet.

* ``ControlNetModel`` builds only the ``UNetMidBlock2DCrossAttn`` and ``UNetMidBlock2D`` middle blocks;
  IF-II's ``UNetMidBlock2DSimpleCrossAttn`` makes ``from_unet`` raise
  ``ValueError: unknown mid_block_type : UNetMidBlock2DSimpleCrossAttn`` for both bases.
* It has no ``cross_attention_norm`` argument, so its ``SimpleCrossAttnDownBlock2D`` lacks IF's
  ``norm_cross`` group norm: with the middle block type changed, copying the down blocks fails
  (``Unexpected key(s) in state_dict: "1.attentions.0.norm_cross.weight", …``).
* The embedding differs even where the weights copy: ``from_unet`` does not pass
  ``addition_embed_type_num_heads`` (the copy's text pooling gets 64 heads, the base has 2: same
  weight shapes, a different function), does not copy ``encoder_hid_proj``, and
  ``ControlNetModel.forward`` applies neither ``encoder_hid_proj`` (the cross-attention would see the
  raw ``encoder_hid_dim`` text embedding) nor ``time_embed_act`` (IF's ``time_embedding_act_fn``), so
  the copied encoder could not reproduce the base's encoder features.
* Its ``ControlNetConditioningEmbedding`` halves the resolution at each width after the first (made
  for Stable Diffusion's 8× latents); this model works in pixel space and the stem keeps full
  resolution (three stride-1 convs, widths 32/48/64). The shipped ``control.safetensors`` holds this
  stem's weights, which have no counterpart there.

So the copy stays explicit below: the same modules ``from_unet`` copies, plus ``encoder_hid_proj`` and
``time_embed_act``, with ``_embedding`` following ``UNet2DConditionModel.forward``.
"""
from __future__ import annotations

import copy

import torch
from torch import nn


def zero_module(m: nn.Module) -> nn.Module:
    for p in m.parameters():
        nn.init.zeros_(p)
    return m


class ConditionStem(nn.Module):
    """aux (C channels, any C) → the base's first feature width; SiLU between 3×3 convs, last one zero."""

    def __init__(self, in_channels: int, out_channels: int, widths=(32, 48, 64)):
        super().__init__()
        layers, c = [], in_channels
        for w in widths:
            layers += [nn.Conv2d(c, w, 3, padding=1), nn.SiLU()]
            c = w
        layers.append(zero_module(nn.Conv2d(c, out_channels, 3, padding=1)))
        self.net = nn.Sequential(*layers)

    def forward(self, aux: torch.Tensor) -> torch.Tensor:
        return self.net(aux)


class ControlModule(nn.Module):
    """Encoder + middle copy of a ``UNet2DConditionModel`` with a condition stem and zero convs."""

    def __init__(self, base, aux_channels: int):
        super().__init__()
        self.aux_channels = int(aux_channels)
        self.conv_in = copy.deepcopy(base.conv_in)
        self.time_proj = copy.deepcopy(base.time_proj)
        self.time_embedding = copy.deepcopy(base.time_embedding)
        self.class_embedding = copy.deepcopy(base.class_embedding)
        self.add_embedding = copy.deepcopy(base.add_embedding)
        self.time_embed_act = copy.deepcopy(base.time_embed_act)
        self.encoder_hid_proj = copy.deepcopy(base.encoder_hid_proj)
        self.down_blocks = copy.deepcopy(base.down_blocks)
        self.mid_block = copy.deepcopy(base.mid_block)
        self.stem = ConditionStem(self.aux_channels, base.conv_in.out_channels)
        self.config = base.config
        self.zero_convs = nn.ModuleList()
        ch = base.conv_in.out_channels
        self.zero_convs.append(zero_module(nn.Conv2d(ch, ch, 1)))
        for block in self.down_blocks:
            for resnet in block.resnets:
                self.zero_convs.append(zero_module(nn.Conv2d(resnet.out_channels, resnet.out_channels, 1)))
            if block.downsamplers is not None:
                for down in block.downsamplers:
                    c = down.out_channels
                    self.zero_convs.append(zero_module(nn.Conv2d(c, c, 1)))
        mid = base.config.block_out_channels[-1]
        self.zero_mid = zero_module(nn.Conv2d(mid, mid, 1))

    def _embedding(self, sample, timestep, class_labels, encoder_hidden_states):
        """The base's time + class + text embedding, computed as ``UNet2DConditionModel.forward`` does."""
        t = timestep if torch.is_tensor(timestep) else torch.tensor([timestep], device=sample.device)
        t = t.to(sample.device).expand(sample.shape[0])
        emb = self.time_embedding(self.time_proj(t).to(sample.dtype))
        if self.class_embedding is not None:
            emb = emb + self.class_embedding(self.time_proj(class_labels).to(sample.dtype))
        if self.add_embedding is not None:
            emb = emb + self.add_embedding(encoder_hidden_states)
        if self.time_embed_act is not None:
            emb = self.time_embed_act(emb)
        if self.encoder_hid_proj is not None:
            encoder_hidden_states = self.encoder_hid_proj(encoder_hidden_states)
        return emb, encoder_hidden_states

    def forward(self, sample, timestep, aux, class_labels, encoder_hidden_states):
        emb, ehs = self._embedding(sample, timestep, class_labels, encoder_hidden_states)
        h = self.conv_in(sample) + self.stem(aux)
        skips = (h,)
        for block in self.down_blocks:
            if getattr(block, "has_cross_attention", False):
                h, res = block(hidden_states=h, temb=emb, encoder_hidden_states=ehs)
            else:
                h, res = block(hidden_states=h, temb=emb)
            skips += res
        if getattr(self.mid_block, "has_cross_attention", False):
            h = self.mid_block(h, emb, encoder_hidden_states=ehs)
        else:
            h = self.mid_block(h, emb)
        down = tuple(zc(s) for zc, s in zip(self.zero_convs, skips, strict=True))
        return down, self.zero_mid(h)


class ControlledDenoiser(nn.Module):
    """Frozen base + Control Module: ``forward(z_t, image, aux, t) → prediction ⊕ variance`` (B, 6, H, W).

    ``control=None`` is the paper's "DeepFloyd-II" ablation: the base alone, same inputs.
    """

    def __init__(self, base, prompt: torch.Tensor, control: ControlModule | None, train_base: bool = False):
        super().__init__()
        self.base = base
        self.control = control
        self.train_base = bool(train_base)
        self.register_buffer("prompt", prompt.detach().clone(), persistent=False)
        self.base.requires_grad_(self.train_base)

    def trainable_parameters(self) -> list[nn.Parameter]:
        params = list(self.control.parameters()) if self.control is not None else []
        return params + (list(self.base.parameters()) if self.train_base else [])

    def train(self, mode: bool = True):
        super().train(mode)
        if not self.train_base:
            self.base.eval()  # frozen: no dropout, whatever the caller does
        return self

    @property
    def multiple(self) -> int:
        """Input sides must be multiples of this (one halving per down block but the last)."""
        return 2 ** (len(self.base.config.block_out_channels) - 1)

    def forward(self, z: torch.Tensor, image: torch.Tensor, aux: torch.Tensor | None, t: torch.Tensor) -> torch.Tensor:
        """``image``: the noisy render (paper) or the first estimate (refine formulation), in model space."""
        sample = torch.cat([z, image], dim=1)
        B = sample.shape[0]
        t = t.expand(B) if t.dim() == 1 and t.numel() == 1 else t
        prompt = self.prompt.to(sample.dtype).expand(B, -1, -1)
        aug = torch.zeros(B, device=sample.device, dtype=torch.long)  # IF's aug_level, fixed to 0 (paper)
        kw = {}
        if self.control is not None:
            down, mid = self.control(sample, t, aux, aug, prompt)
            kw = {"down_block_additional_residuals": down, "mid_block_additional_residual": mid}
        return self.base(sample, t, encoder_hidden_states=prompt, class_labels=aug, **kw).sample
