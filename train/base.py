"""The frozen base: a ``diffusers`` ``UNet2DConditionModel`` in DeepFloyd IF stage II's layout.

IF-II is a super-resolution model: its input is ``z_t ⊕ upsampled low-res image`` (6 channels),
its output ``ε̂ ⊕ v`` (6: noise and learned-range variance), the augmentation noise level enters
through ``class_embed_type="timestep"`` (we fix it to 0, as the paper), and a T5 text embedding
enters through ``encoder_hid_dim``/``addition_embed_type="text"``. The paper feeds the noisy
render where IF expects the upsampled image, and the empty prompt.

A base is a folder in the ``diffusers`` layout, so a real checkpoint and ours load alike::

    BASE/config.json                          UNet2DConditionModel config
    BASE/diffusion_pytorch_model.safetensors  weights
    BASE/prompt_embeds.safetensors            tensor "prompt_embeds" (1, L, encoder_hid_dim):
                                              the empty prompt's text embedding

For DeepFloyd IF-II-M: point ``diffusion.base`` at its ``unet/`` folder and save T5-XXL's
embedding of "" there as ``prompt_embeds.safetensors`` (see README). Nothing is ever downloaded
(``local_files_only=True``).

``default_config`` is the small stand-in we train ourselves (``make pretrain``): the same block
types as IF-II (ResNet down/up blocks with scale-shift time conditioning, simple cross-attention
at the lowest resolution, GELU), far fewer channels.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch

from mcdenoise.pipeline.errors import CheckpointError
from mcdenoise.pipeline.exr import atomic_write_bytes, atomic_write_json

WEIGHTS = "diffusion_pytorch_model.safetensors"
PROMPT = "prompt_embeds.safetensors"
PROMPT_TOKENS = 8
# The paper formulation's stand-in base shipped with the repository (an IF-II-style super-resolution
# prior, ε-prediction with learned variance; train/base_model_paper/README.md).
PAPER_BASE = Path(__file__).resolve().parent / "base_model_paper"


def default_config(channels: list[int], layers_per_block: int = 1, text_dim: int = 64,
                   attention_head_dim: int = 32) -> dict:
    """An IF-II-layout UNet config with ``channels`` per level (the last level has attention)."""
    n = len(channels)
    return {
        "sample_size": 64, "in_channels": 6, "out_channels": 6, "layers_per_block": int(layers_per_block),
        "block_out_channels": list(channels),
        "down_block_types": ["ResnetDownsampleBlock2D"] * (n - 1) + ["SimpleCrossAttnDownBlock2D"],
        "up_block_types": ["SimpleCrossAttnUpBlock2D"] + ["ResnetUpsampleBlock2D"] * (n - 1),
        "mid_block_type": "UNetMidBlock2DSimpleCrossAttn",
        "cross_attention_dim": channels[-1], "encoder_hid_dim": int(text_dim),
        "attention_head_dim": int(attention_head_dim), "addition_embed_type": "text",
        "addition_embed_type_num_heads": 2, "cross_attention_norm": "group_norm",
        "resnet_time_scale_shift": "scale_shift", "act_fn": "gelu", "class_embed_type": "timestep",
        "mid_block_scale_factor": 1.414, "time_embedding_act_fn": "gelu", "norm_num_groups": 16,
    }


def build(config: dict, seed: int = 0):
    """A freshly initialised base and a fixed stand-in for the empty prompt's embedding."""
    from diffusers import UNet2DConditionModel

    torch.manual_seed(seed)
    unet = UNet2DConditionModel(**config)
    g = torch.Generator().manual_seed(seed)
    prompt = torch.randn(1, PROMPT_TOKENS, int(config["encoder_hid_dim"]), generator=g) * 0.5
    return unet, prompt


def check_layout(unet, source) -> None:
    """The base must take and return 6 channels (IF-II: z_t ⊕ image → ε ⊕ variance)."""
    cfg = unet.config
    if cfg.in_channels != 6 or cfg.out_channels != 6:
        raise CheckpointError(f"{source}: base UNet has in/out channels {cfg.in_channels}/{cfg.out_channels}, expected 6/6 "
                              "(the IF stage II layout: noisy sample + low-quality image in, epsilon + variance out)")


def load(folder: str | Path, dtype: torch.dtype = torch.float32):
    """(unet, prompt_embeds) from a base folder in the diffusers layout (never downloads)."""
    from diffusers import UNet2DConditionModel
    from safetensors.torch import load_file

    folder = Path(folder)
    for name in ("config.json", WEIGHTS, PROMPT):
        if not (folder / name).is_file():
            raise CheckpointError(f"{folder / name}: missing; a base folder needs config.json, {WEIGHTS} and {PROMPT} "
                                  "(run `make pretrain`, or see the README for DeepFloyd IF-II)")
    try:
        unet = UNet2DConditionModel.from_pretrained(str(folder), local_files_only=True, torch_dtype=dtype, low_cpu_mem_usage=False,
                                                    use_safetensors=True)
    except (OSError, ValueError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{folder}: cannot load the base UNet: {exc}") from exc
    check_layout(unet, folder)
    tensors = load_file(str(folder / PROMPT))
    if "prompt_embeds" not in tensors:
        raise CheckpointError(f"{folder / PROMPT}: no tensor named 'prompt_embeds'")
    prompt = tensors["prompt_embeds"].to(dtype)
    hid = unet.config.encoder_hid_dim or unet.config.cross_attention_dim
    if prompt.dim() != 3 or prompt.shape[0] != 1 or prompt.shape[-1] != hid:
        raise CheckpointError(f"{folder / PROMPT}: prompt_embeds has shape {tuple(prompt.shape)}, expected (1, L, {hid})")
    return unet, prompt


def save(folder: str | Path, unet, prompt: torch.Tensor, card: dict | None = None) -> None:
    """Write a base folder (atomically per file) that ``load`` reads back."""
    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_json(folder / "config.json", dict(unet.config) | {"_class_name": "UNet2DConditionModel"})
    state = {k: v.detach().contiguous().cpu() for k, v in unet.state_dict().items()}
    atomic_write_bytes(folder / WEIGHTS, lambda tmp: save_file(state, tmp, metadata={"format": "pt"}))
    atomic_write_bytes(folder / PROMPT, lambda tmp: save_file({"prompt_embeds": prompt.detach().contiguous().cpu()},
                                                               tmp))
    if card is not None:
        atomic_write_json(folder / "training.json", card)


def write_new(folder: str | Path, channels: list[int], layers_per_block: int = 1, seed: int = 0) -> Path:
    """A new base in ``default_config``'s layout whose last convolution is zero: with the refine
    formulation it returns its image input (the first estimate) exactly; it has to train with the
    Control Module (``diffusion.train_base``), since a frozen zero layer passes no gradient back."""
    from torch import nn

    unet, prompt = build(default_config(list(channels), layers_per_block), seed=seed)
    for p in unet.conv_out.parameters():
        nn.init.zeros_(p)
    save(folder, unet, prompt, {"what": "new base, last convolution zero (train/base.py: write_new)", "seed": seed})
    return Path(folder)
