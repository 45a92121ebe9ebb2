"""Typed configuration: YAML (``yaml.safe_load``) → nested dataclasses, with ``key=value`` overrides.

Every field carries its documentation in ``metadata["doc"]``; ``configs/README.md`` is generated
from it (``python -m pipeline config --doc``) and a test keeps the two in sync, so a key cannot be
added without being documented. Unknown keys and wrongly typed values are errors that name the
file and the dotted key.

Each section (a ``Section``) holds the value checks of its own keys in ``check``; ``validate``
runs them all after loading. The trainer sections (clean, afgsa, diffusion, oidn_ft)
share the settings of ``TrainingConfig``, declared, documented and checked there once. The rules
of the diffusion formulation keys (``check_formulation``) live here too, for ``DiffusionConfig``
and for ``train.sampler.Formulation``, which is also built from model.json records.
"""
from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import yaml

from .errors import ConfigError

# bad(key, message) raises: the key relative to the section being checked (validate names the section).
Bad = Callable[[str, str], NoReturn]


def doc(text: str, default: Any = dataclasses.MISSING, factory: Any = dataclasses.MISSING):
    """A dataclass field with documentation attached."""
    if factory is not dataclasses.MISSING:
        return field(default_factory=factory, metadata={"doc": text})
    return field(default=default, metadata={"doc": text})


def required(text: str):
    """A documented field without a default, for a base class whose subclasses each give their own.
    Keyword-only, because it may follow fields that have defaults."""
    return field(kw_only=True, metadata={"doc": text})


class Section:
    """A config section; ``check`` holds the value checks of its keys that types alone cannot express."""

    def check(self, bad: Bad) -> None:
        """Call ``bad(key, message)`` for the first value that cannot work; this section has no such rule."""

    def at_least(self, bad: Bad, minimum: float, *keys: str) -> None:
        """Each of ``keys`` must be >= ``minimum``."""
        for key in keys:
            if getattr(self, key) < minimum:
                bad(key, f"must be >= {minimum}")

    def one_of(self, bad: Bad, key: str, choices: tuple) -> None:
        """``key`` must be one of ``choices``."""
        value = getattr(self, key)
        if value not in choices:
            names = [repr(c) for c in choices]
            bad(key, f"expected {', '.join(names[:-1])} or {names[-1]}, got {value!r}")


@dataclass
class TrainingConfig(Section):
    """The settings every trainer section has (clean, afgsa, diffusion, oidn_ft), each with one
    meaning in all of them: declared, documented and checked here once. A section re-declares one with
    ``override`` to give its own default or add to the doc; epochs and lr have no common default, so
    every section gives its own."""
    epochs: int = required("Training epochs.")
    batch_size: int = doc("Crops per optimisation step.", 8)
    crop: int = doc("Side of the random training crops in pixels.", 64)
    lr: float = required("Learning rate.")
    grad_clip: float = doc("Clip the gradient's global L2 norm to this value (0: no clipping).", 1.0)
    nan_limit: int = doc("A step whose loss or gradient is not finite is skipped and counted; training stops with "
                         "an error after this many such steps in a row.", 10)
    time_budget_s: float = doc("Stop at the end of the epoch during which this many seconds of training have passed, "
                               "counted from the data loaded (a training pack built first does not count; 0: no "
                               "limit); the best and the last checkpoint are kept, a rerun resumes.", 0.0)
    device: str = doc("Torch device: 'auto' (CUDA if available), 'cpu', 'cuda', ...", "auto")

    def check(self, bad: Bad) -> None:
        self.check_epochs(bad)
        self.at_least(bad, 1, "batch_size", "crop", "nan_limit")
        self.at_least(bad, 0, "grad_clip", "time_budget_s")
        if not self.lr > 0:
            bad("lr", "must be > 0")

    def check_epochs(self, bad: Bad) -> None:
        self.at_least(bad, 1, "epochs")


def override(name: str, default: Any, more: str = "", parent: type = TrainingConfig):
    """Re-declare ``parent``'s field ``name`` in a subclass or a sibling section: its own default, the
    parent's doc with ``more`` (what the section adds to the meaning) after it."""
    text = parent.__dataclass_fields__[name].metadata["doc"]
    return doc(f"{text} {more}" if more else text, default)


@dataclass
class DatasetConfig(Section):
    scenes: int = doc("Number of random scenes.", 24)
    frames: int = doc("Frames per scene along the random camera move (paper: 8).", 2)
    resolution: list = doc("Image size [width, height] in pixels (paper: [256, 256]).", factory=lambda: [128, 128])
    gt_spp: int = doc("Samples per pixel of each of the two ground truths GT1, GT2 (paper: 4096) when "
                      "gt_target_psnr is null.", 1024)
    gt_target_psnr: float | None = doc(
        "Render GT1 and GT2 progressively to this error: the PSNR in dB (Reinhard tonemap, peak 1, as the metric) "
        "that each is expected to have against the true image, estimated from its per-pixel variance; passes of "
        "gt_pass_spp are pooled exactly until an image reaches it or gt_max_spp (docs/store.md). null: one render "
        "of gt_spp.", None)
    gt_pass_spp: int = doc("Samples per pixel of one pass of a progressive ground truth (also its minimum spp).", 64)
    gt_max_spp: int = doc("Most samples per pixel of a progressive ground truth (a multiple of gt_pass_spp).", 1024)
    stack_spp: int = doc("Samples per pixel of one low-spp stack (paper: 4).", 4)
    stacks: int = doc("Low-spp stacks per frame; spp 4/16/64 average 1/4/16 stacks (paper: 16).", 16)
    val_fraction: float = doc("Fraction of scenes in the validation split (paper: 0.03); at least one scene.", 0.03)
    test_fraction: float = doc("Fraction of scenes in the test split (paper: 0.05); at least one scene.", 0.05)
    stress: list = doc("Names of stress presets rendered as extra scenes in the split 'stress' (see render/stress.py); "
                       "'all' for every preset.", factory=list)
    stress_copies: int = doc("Variants of each stress preset (copy k > 0 is scene stress_<name>_<k>, another seed of "
                             "the same preset): oversamples hard light transport in a training set.", 1)
    stress_split: str = doc("'stress': stress scenes form their own split (reported apart by make eval); 'mixed': "
                            "they are split into train/val/test with the random scenes (a training set).", "stress")


    def check(self, bad: Bad) -> None:
        self.at_least(bad, 1, "scenes", "frames")
        if (not isinstance(self.resolution, list) or len(self.resolution) != 2
                or not all(isinstance(v, int) and v > 0 for v in self.resolution)):
            bad("resolution", f"expected [width, height] of positive integers, got {self.resolution!r}")
        self.at_least(bad, 1, "gt_spp", "stack_spp", "stacks")
        self.check_progressive_gt(bad)
        if (not 0 <= self.val_fraction < 1 or not 0 <= self.test_fraction < 1
                or self.val_fraction + self.test_fraction >= 1):
            bad("val_fraction/test_fraction", "fractions in [0, 1) that sum to less than 1")
        # The names in dataset.stress are checked by render.dataset, which knows the presets.
        if self.stress_copies < 1:
            bad("stress_copies", f"expected >= 1, got {self.stress_copies}")
        self.one_of(bad, "stress_split", ("stress", "mixed"))

    def check_progressive_gt(self, bad: Bad) -> None:
        if self.gt_target_psnr is None:
            return
        if not math.isfinite(self.gt_target_psnr) or self.gt_target_psnr <= 0:
            bad("gt_target_psnr", f"expected a positive number of dB or null, got {self.gt_target_psnr!r}")
        if self.gt_pass_spp < 2:
            bad("gt_pass_spp", f"must be >= 2 (a pass's variance needs two samples), got {self.gt_pass_spp}")
        if self.gt_max_spp < self.gt_pass_spp or self.gt_max_spp % self.gt_pass_spp:
            bad("gt_max_spp", f"must be a multiple of gt_pass_spp ({self.gt_pass_spp}), got {self.gt_max_spp}")


@dataclass
class SceneConfig(Section):
    objects: list = doc("Range [min, max] of objects per scene.", factory=lambda: [3, 7])
    mesh_dirs: list = doc("Folders of user meshes (OBJ/PLY/STL/OFF/GLB, e.g. ShapeNet) mixed into the scenes.", factory=list)
    mesh_probability: float = doc("Probability that an object is drawn from mesh_dirs (when any are given).", 0.5)
    texture_probability: float = doc("Probability that a material's base colour is a procedural texture.", 0.5)
    polished_probability: float = doc("Probability that the ground (and, in a room, the walls) is polished: a "
                                      "smooth plastic or principled coat reflecting the scene sharply; 0: matte-ish "
                                      "surfaces only (the scenes made before this key existed).", 0.0)
    enclosed_probability: float = doc("Probability that the scene is a closed room (four walls and a ceiling) "
                                      "lit through one or two windows by a sky outside, half the time with no "
                                      "light inside: interiors lit mostly indirectly; 0: open sets only (the "
                                      "scenes made before this key existed).", 0.0)
    sun_delta_probability: float = doc("Probability that a sky's sun is a delta (directional) light: sharp shadows, as "
                                       "the sun lights of Blender, Houdini and USD throw, instead of a 3-8 degree "
                                       "blob in the sky map (soft shadows) with the same irradiance; 0: blob suns only "
                                       "(the scenes made before this key existed).", 0.0)
    interior_probability: float = doc("Probability that a scene is a furnished interior (render/interior.py, "
                                      "docs/scenes.md): a room of varied plan with furniture and props, lit by "
                                      "shaded lamps, daylight through windows, hidden cove or recessed lights, or "
                                      "only from a neighbouring room; the camera inside at eye height. Drawn first; "
                                      "0: none (the scenes made before this key existed).", 0.0)
    product_probability: float = doc("Probability that a scene not drawn as an interior is a product shot "
                                     "(render/product.py): glossy, metal and glass products on a sweep or a table "
                                     "under softboxes and strip lights, a close tele camera; 0: none (the scenes "
                                     "made before this key existed).", 0.0)
    group_probability: float = doc("Probability that an object is a grouped composition of primitives.", 0.2)
    materials: dict = doc("Relative weights of material families: principled, diffuse, plastic, roughplastic, "
                          "conductor, roughconductor, dielectric, roughdielectric.",
                          factory=lambda: {"principled": 4.0, "diffuse": 1.0, "plastic": 1.0, "roughplastic": 1.0,
                                           "conductor": 0.7, "roughconductor": 0.7, "dielectric": 0.5,
                                           "roughdielectric": 0.4})
    area_lights: list = doc("Range [min, max] of rectangular/spherical area lights.", factory=lambda: [1, 3])
    small_light_probability: float = doc("Probability that an area light is small and very bright.", 0.25)
    point_light_probability: float = doc("Probability of adding a point light.", 0.3)
    spot_light_probability: float = doc("Probability of adding a spot light.", 0.3)
    environment_probability: float = doc("Probability of an environment (procedural sky or constant).", 0.7)
    walls_probability: float = doc("Probability of walls behind the objects (a ground plane is always present).", 0.6)
    fov: list = doc("Range [min, max] of the camera's horizontal field of view in degrees.", factory=lambda: [35.0, 65.0])
    camera_move: float = doc("Length of the smooth random camera move over all frames, relative to the camera distance.", 0.25)


    def check(self, bad: Bad) -> None:
        for key in ("objects", "area_lights", "fov"):
            rng = getattr(self, key)
            numbers = isinstance(rng, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in rng)
            if not (numbers and len(rng) == 2 and rng[0] <= rng[1]):
                bad(key, f"expected a range [min, max], got {rng!r}")
        for f in dataclasses.fields(self):
            if f.name.endswith("_probability") and not 0 <= getattr(self, f.name) <= 1:
                bad(f.name, f"expected a probability in [0, 1], got {getattr(self, f.name)!r}")


@dataclass
class RenderConfig(Section):
    variant: str = doc("Mitsuba variant: 'auto' (cuda_ad_rgb with a GPU, else llvm_ad_rgb), or an explicit one "
                       "such as llvm_ad_rgb, cuda_ad_rgb, scalar_rgb.", "auto")
    max_depth: int = doc("Maximum path length (Mitsuba convention: 1 = directly visible emission only).", 8)
    rr_depth: int = doc("Path depth at which Russian roulette starts.", 5)
    features: str = doc("'auto': compute only the features the scene's materials can produce; 'all': every feature.", "auto")
    omit_constant: bool = doc("Leave out channels that are constant over a frame; the EXR header records the constant.", True)
    encoding: str = doc("How new store images are written (docs/store.md, 'Encodings'): 'compact' (the beauty "
                        "summed from its components, variances and depth float32 with 5 and 10 mantissa bits, "
                        "ZIP: any OpenEXR reader opens it), 'compact-zstd' (the same values with ZSTD: smaller, "
                        "needs OpenEXR >= 3.5 to read) or 'exact' (every value as rendered, ZIP). All read "
                        "the same way.", "compact")
    threads: int = doc("drjit worker threads per render process (0: all cores).", 0)


    def check(self, bad: Bad) -> None:
        self.one_of(bad, "features", ("auto", "all"))
        self.one_of(bad, "encoding", ("compact", "compact-zstd", "exact"))
        self.at_least(bad, 1, "max_depth")


@dataclass
class ExecutorConfig(Section):
    kind: str = doc("'local' (worker processes on this machine) or 'ray' (Ray tasks, local or a cluster).", "local")
    workers: int = doc("Parallel frames for the local executor (each uses render.threads threads).", 1)
    address: str = doc("Ray cluster address for kind=ray (e.g. 'ray://head:10001' or 'auto'); empty: start a local Ray.", "")
    ray_cpus_per_task: float = doc("CPUs Ray reserves per frame task.", 1.0)
    retries: int = doc("How often a frame whose worker died (native crash, killed node) is retried.", 2)


    def check(self, bad: Bad) -> None:
        self.one_of(bad, "kind", ("local", "ray"))
        self.at_least(bad, 1, "workers")


@dataclass
class CleanConfig(TrainingConfig):
    epochs: int = override("epochs", 12, "The GT cleaner's loss is SMAPE, GT1 -> GT2 swapped at random; with the "
                                         "range term its val score flattens after about 6 epochs on the default "
                                         "dataset.")
    lr: float = override("lr", 1e-3, "Optimiser: AdamW.")
    grad_clip: float = override("grad_clip", 1.0, "HDR outliers otherwise make single steps huge.")
    weight_decay: float = doc("AdamW weight decay.", 1e-4)
    crops_per_frame: int = doc("Random crops drawn from each training frame per epoch.", 4)
    smape_eps: float = doc("epsilon of SMAPE(A, B) = |A - B|_1 / (|A|_1 + |B|_1 + eps) (paper eq. 2).", 1e-2)
    kernel_size: int = doc("Side of each dilated affinity kernel.", 7)
    dilations: list = doc("Dilation of each of the K iterated kernels (Isik et al.: 1, 2, 4).", factory=lambda: [1, 2, 4])
    channels: list = doc("U-Net channels per level (Isik et al.: 64, 64, 80, 96; smaller for CPU).",
                         factory=lambda: [32, 48, 64])
    embed_channels: int = doc("Channels of the per-pixel embedding.", 32)
    affinity_channels: int = doc("Channels of the affinity features f_p per iteration.", 8)
    range_term: bool = doc("Add the variance-normalized NL-means distance of Rousselle et al. 2012 to every "
                           "kernel's log-weights, with a learned per-pixel weight (clean.model.range_distance). "
                           "Off: learned affinity features only, as in Isik et al.", True)
    range_patch: int = doc("Patch radius of the range distance (0: per pixel; 1: 3x3 patches).", 1)
    tile: int = doc("Inference tile side in pixels: larger frames are denoised in overlapping tiles "
                    "(bounded memory).", 512)

    def check(self, bad: Bad) -> None:
        super().check(bad)
        self.at_least(bad, 1, "crops_per_frame")


@dataclass
class AfgsaConfig(TrainingConfig):
    epochs: int = override("epochs", 12, "An epoch: crops_per_frame crops of every train frame. A fixed epoch "
                                         "count rather than a time budget, so that two runs write the same weights "
                                         "on loaded and idle cores.")
    crop: int = override("crop", 64, "Paper: 128.")
    lr: float = override("lr", 5e-4, "Of the generator; optimiser: Adam (paper: 1e-4; higher for minutes of CPU "
                                       "training).")
    grad_clip: float = override("grad_clip", 1.0, "The generator's and the critic's gradient, each.")
    target: str = doc("Training target: 'gt_clean' (as the paper) or 'gt1' (the raw reference; the GT_clean-vs-GT1 "
                      "experiment). gt1 runs are kept apart, in runs/<..>/afgsa_gt1_spp<N>.", "gt_clean")
    crops_per_frame: int = doc("Random crops drawn from each training frame per epoch.", 4)
    lr_critic: float = doc("Adam learning rate of the discriminator (paper: 1e-4).", 5e-4)
    adv_weight: float = doc("Weight of the adversarial (WGAN-GP) term in the generator loss, next to L1 in log "
                            "space with weight 1 (paper: 5e-3). 0: the L1-only ablation, no discriminator trained.",
                            5e-3)
    gp_weight: float = doc("Weight of the discriminator's gradient penalty (WGAN-GP; paper: 10).", 10.0)
    channels: int = doc("Feature channels of the transformer blocks (paper: 256).", 32)
    extractor_channels: int = doc("Channels of each 1x1/3x3/5x5 branch of the multi-scale feature extractors "
                                  "(paper: 256).", 32)
    blocks: int = doc("Transformer blocks with auxiliary-feature-guided self-attention (paper: 5).", 2)
    heads: int = doc("Attention heads; channels / heads must be even (paper: 4).", 2)
    block_size: int = doc("Side of the square query blocks of the block-wise attention (paper: 8).", 8)
    halo: int = doc("Halo around each block: its pixels attend to the (block_size + 2 halo)^2 neighbourhood "
                    "(paper: 3).", 3)
    critic_channels: int = doc("Channels of the patch discriminator's first layer, doubled at each stride-2 level "
                               "(the paper's VGG-style critic: 64).", 16)
    critic_levels: int = doc("Stride-2 levels of the patch discriminator.", 3)
    tile: int = doc("Inference tile side in pixels; larger frames are denoised in overlapping tiles (bounded "
                    "memory).", 256)

    def check(self, bad: Bad) -> None:
        super().check(bad)
        self.one_of(bad, "target", ("gt_clean", "gt1"))
        self.at_least(bad, 1, "crops_per_frame", "channels", "extractor_channels", "heads", "block_size",
                      "critic_channels", "tile")
        if self.blocks < 0 or self.halo < 0 or self.critic_levels < 0:
            bad("blocks/halo/critic_levels", "must be >= 0")
        if self.channels % self.heads or (self.channels // self.heads) % 2:
            bad("channels/heads", f"{self.channels} channels must split into {self.heads} heads of an even size")
        if self.adv_weight < 0 or self.gp_weight < 0:
            bad("adv_weight/gp_weight", "must be >= 0")


PRECISIONS = ("auto", "fp32", "bf16")   # diffusion.precision


# ---- the diffusion formulation -------------------------------------------------------------------
# What the diffusion model diffuses and how it samples (train/sampler.py). The choices of its keys
# and their rules live here, where both the config and train.sampler.Formulation read them.

SCHEDULES = ("if", "zero_snr")
STARTS = ("noise", "render", "estimate")
TRAIN_STEPS = 1000   # IF's training timesteps; the sampler spaces `steps` of them


def check_formulation(f, bad: Bad) -> None:
    """Refuse formulation fields that cannot work: ``f`` is a ``DiffusionConfig`` or a
    ``train.sampler.Formulation``, ``bad`` gets the key inside the ``diffusion`` section."""
    for key, choices in (("schedule", SCHEDULES), ("start", STARTS)):
        if getattr(f, key) not in choices:
            bad(key, f"expected one of {', '.join(choices)}, got {getattr(f, key)!r}")
    if not f.residual_scale > 0:
        bad("residual_scale", f"expected > 0, got {f.residual_scale}")
    if not 0 <= f.t_focus <= 1:
        bad("t_focus", f"expected a probability in [0, 1], got {f.t_focus}")
    if not f.snr_gamma > 0:
        bad("snr_gamma", f"expected > 0, got {f.snr_gamma}")
    if not f.snr_floor >= 0:
        bad("snr_floor", f"expected >= 0, got {f.snr_floor}")
    if not 1 <= f.steps <= TRAIN_STEPS:
        bad("steps", f"need 1 <= steps <= {TRAIN_STEPS}, got {f.steps}")
    if not 0 <= f.skip < f.steps:
        bad("skip", f"need 0 <= skip < steps ({f.steps}), got {f.skip}")
    if f.start == "noise" and f.skip:
        bad("skip", f"sampling from pure noise starts at t = T: skip must be 0, got {f.skip}")


# OIDN networks a Control Module can sit on (colour + albedo + normal, as rendered or prefiltered)
BASE_NETWORKS = ("rt_hdr_alb_nrm", "rt_hdr_calb_cnrm", "rt_hdr_calb_cnrm_large")


@dataclass
class DiffusionConfig(TrainingConfig):
    """The diffusion denoiser: a Control Module on OIDN's frozen network. The defaults are the recipe of the
    shipped model (train/shipped/model.json "settings")."""
    base: str = doc("The frozen base the Control Module sits on (train/model.py): 'oidn' (OIDN's own "
                    "base_network, weights from oidn.weights or pyoidn), 'oidn_ft' (this config's oidn_ft run of "
                    "base_network, make train MODEL=oidn_ft) or a .tza file of base_network's weights.", "oidn")
    base_network: str = doc("Which of OIDN's networks is the base: 'rt_hdr_calb_cnrm_large' (OIDN's final-frame "
                            "mode, the oidn_prefilter row: albedo and normal first denoised by OIDN's aux networks; "
                            "the 3.9 M-parameter UNetLarge), 'rt_hdr_calb_cnrm' (the same, small) or "
                            "'rt_hdr_alb_nrm' (what make eval's oidn row runs: colour, albedo and normal as "
                            "rendered; 2.4x faster to train).", "rt_hdr_calb_cnrm_large")
    extra_stores: list = doc("More stores whose train splits train the Control Module with the config's own (one "
                             "pack each, beside it in <runs>/pack/); validation stays on the config's store. E.g. "
                             "renders of your own scenes added to the ship data.", factory=list)
    init: str = doc("A trained model folder (a run folder or an exported one such as train/shipped) the run "
                    "starts from: its frozen base replaces diffusion.base and its Control Module trains on (a warm "
                    "start, e.g. on new data) with that model's formulation and train_steps (the config's are not "
                    "used; the run says which differ); empty: a new, zero-initialised Control Module.", "")
    model: str = doc("A model folder (a run folder or an exported one) that the methods without a run variant "
                     "(ours, ours_filter, ours_temporal) and denoise run, whatever the runs folder holds: to score "
                     "a model trained on another store on this one. Empty: this config's run, else train/shipped.",
                     "")
    epochs: int = override("epochs", 16, "An epoch: crops_per_frame crops of every train frame, at most "
                                         "epoch_steps steps.")
    batch_size: int = override("batch_size", 8, "Per process under torchrun.")
    crop: int = override("crop", 64, "A multiple of 16 (OIDN's alignment).")
    loader_workers: int = doc("Processes that cut and augment the training crops beside the training process (0: "
                              "in it). A GPU steps faster than one CPU core cuts crops: give it several.", 0)
    lr: float = override("lr", 2e-4, "Optimiser: AdamW on the Control Module.")
    crops_per_frame: int = doc("Random crops drawn from each training frame per epoch.", 2)
    epoch_steps: int = doc("At most this many steps per epoch, on a random subset of the epoch's crops (new each epoch), "
                           "so validation, checkpoints and the time budget come that often on a large training set; "
                           "0: every crop.", 80)
    weight_decay: float = doc("AdamW weight decay.", 0.01)
    warmup_steps: int = doc("Linear learning-rate warm-up steps, then a cosine decay to 0 over the run.", 100)
    keep_epochs: list = doc("Epochs whose EMA Control Module is kept as well as the best one, each a model folder "
                            "<run>/epoch<N>: the best is chosen on the config's val split alone, which a long run "
                            "can fit while it loses on scenes unlike the training data (docs/diffusion.md).",
                            factory=list)
    precision: str = doc("'auto' (bf16 autocast on CUDA, fp32 on CPU), 'fp32' or 'bf16'.", "auto")
    shipped: bool = doc("Use the denoiser shipped in train/shipped wherever this config has no trained run of its "
                        "own (make eval's ours rows, make denoise), and its oidn_ft weights for make eval's "
                        "oidn_ft_albedo and oidn_ft_color rows.", True)
    name: str = doc("Run variant: the run folder is diffusion_spp<N>[_<name>] (e.g. 'large' beside the default "
                    "one); make eval's ours_<name> rows read it.", "")
    schedule: str = doc("Noise schedule: 'zero_snr' (IF's cosine betas rescaled to zero terminal SNR, trailing "
                        "timesteps, Lin et al. 2023: one step from t = T is the network's direct estimate) or 'if' "
                        "(IF's cosine schedule as is).", "zero_snr")
    residual_scale: float = doc("Scale s of the diffused residual (x - x_est)/s around the base's output in OIDN's "
                                "output space (about its standard deviation over the training pairs, so the residual "
                                "is of unit order).", 0.02)
    snr_gamma: float = doc("gamma of the min-SNR loss weighting (Hang et al. 2023).", 5.0)
    snr_floor: float = doc("Floor of the min-SNR weight in x0-error terms (min(SNR, gamma) is 0 at SNR = 0, the "
                           "step whose output is the one-step estimate).", 1.0)
    hdr_weight: float = doc("Weight of the second loss term, the L1 in OIDN's PU space relative to OIDN's own "
                            "(highlights keep their relative error there, as HDR-FLIP sees them), beside the "
                            "tonemapped MSE relative to OIDN's (what PSNR reads); train/loss.py.", 0.5)
    dropout: float = doc("Probability that a training crop lacks a buffer group (the variances, the radiance split, "
                         "the material buffers; each on its own), so one model serves inputs without them.", 0.15)
    history: bool = doc("The model reads the past (docs/sequences.md): its condition gets the previous frame's "
                        "output warped into this frame, its validity and has.history; it trains on the frames t >= 1 "
                        "(0-based) of each scene, their input averaged as the temporal methods average it "
                        "(eval.temporal_window, eval.temporal_gate), their history OIDN's final-frame output of "
                        "frame t-1's averaged input, warped with the noisy input's depth and normal; its packs are "
                        "<split>_oidn_base*_history. With init, a "
                        "model without history starts with the new channels' weights zero (it starts as that "
                        "model). false: the per-frame model (44 condition channels).", False)
    history_dropout: float = doc("With history: probability that a training crop has no history (its history "
                                 "channels and has.history zero, as on a sequence's first frame), so the model "
                                 "keeps serving single frames.", 0.25)
    t_focus: float = doc("Probability that a training timestep is drawn from the timesteps the sampler visits with "
                         "one of train_steps steps (else uniform over 0..999).", 0.9)
    train_steps: list = doc("Step counts whose timesteps t_focus draws from (each count equally likely).",
                            factory=lambda: [1])
    steps: int = doc("Sampler steps (DDIM, trailing spacing over the 1000 training steps).", 1)
    start: str = doc("Where sampling starts: 'estimate' (the base's output q-sampled at the first step run), "
                     "'render' (the noisy render q-sampled there) or 'noise' (pure noise at t = T).", "estimate")
    samples: int = doc("Samples averaged per frame by make denoise (their per-pixel standard deviation is the "
                       "uncertainty layer of denoise's output).", 1)
    skip: int = doc("Sampler steps skipped at the start (of the 'steps' trailing steps).", 0)
    ema: float = doc("Decay of an exponential moving average of the trained weights (diffusers' EMAModel, with "
                     "its warm-up), which is what validation scores and the run saves; 0: the weights themselves.",
                     0.999)
    val_frames: int = doc("Validation frames sampled after every epoch and before the first (val PSNR with the "
                          "configured sampler, at the run's smallest, middle and largest spp).", 16)

    def check(self, bad: Bad) -> None:
        super().check(bad)
        self.at_least(bad, 1, "crops_per_frame", "samples")
        self.at_least(bad, 0, "warmup_steps", "val_frames", "loader_workers")
        if not 0.0 <= self.history_dropout <= 1.0:
            bad("history_dropout", f"must be a probability in [0, 1], got {self.history_dropout}")
        if self.epoch_steps < 0:
            bad("epoch_steps", f"must be >= 0 (0: every crop), got {self.epoch_steps}")
        if self.crop % 16:
            bad("crop", f"must be a multiple of 16 (OIDN's alignment), got {self.crop}")
        check_formulation(self, bad)
        if not self.train_steps or not all(isinstance(n, int) and 1 <= n <= TRAIN_STEPS for n in self.train_steps):
            bad("train_steps", f"expected step counts from 1 to {TRAIN_STEPS}, got {self.train_steps!r}")
        if not all(isinstance(n, int) and n >= 1 for n in self.keep_epochs):
            bad("keep_epochs", f"expected epoch numbers >= 1, got {self.keep_epochs!r}")
        self.one_of(bad, "precision", PRECISIONS)
        if self.base not in ("oidn", "oidn_ft") and not self.base.endswith(".tza"):
            bad("base", f"expected 'oidn', 'oidn_ft' or a .tza file of OIDN's weights, got {self.base!r}")
        if self.init and not (Path(self.init) / "model.json").is_file():
            bad("init", f"{self.init}: not a trained model folder (no model.json there)")
        self.one_of(bad, "base_network", BASE_NETWORKS)
        for root in self.extra_stores:
            if not (Path(root) / "dataset.json").is_file():
                bad("extra_stores", f"{root}: no dataset there (no dataset.json); render it: make dataset store={root}")


@dataclass
class OidnConfig(Section):
    weights: str = doc("Where OIDN's trained weights are read from (the prior of oidn_ft and of the diffusion "
                       "base): empty: the blobs inside pyoidn's library (Linux); else a .tza file (used for the "
                       "network being loaded) or a folder of <network>.tza files, as OIDN's public weights "
                       "repository has them (the way on macOS and Windows). The baseline rows (oidn, oidn_color) "
                       "always run pyoidn's built-in weights.", "")


@dataclass
class OidnFtConfig(TrainingConfig):
    epochs: int = override("epochs", 30, "An epoch: crops_per_frame crops of every train frame, at most epoch_steps "
                                         "steps.")
    crop: int = override("crop", 64, "A multiple of 16, OIDN's alignment.")
    lr: float = override("lr", 5e-5, "Optimiser: Adam; reached after the warm-up, then a cosine decay to lr_end "
                                       "over the run.")
    network: str = doc("OIDN network fine-tuned by make train MODEL=oidn_ft: 'rt_hdr_alb_nrm' (colour + albedo + "
                       "normal: what make eval's oidn row runs), 'rt_hdr_alb' (+ albedo: the oidn_ft_albedo row) or "
                       "'rt_hdr' (colour only: the oidn_ft_color row); a '_small' variant of each also loads; "
                       "'rt_hdr_calb_cnrm_large' (the oidn_ft_prefilter row) or 'rt_hdr_calb_cnrm' fine-tune OIDN's "
                       "final-frame mode (albedo and normal prefiltered by OIDN's aux networks: per 4-spp stack for "
                       "training, as a whole at validation and use). Its run folder is "
                       "<runs>/oidn_ft_<network>.", "rt_hdr_alb_nrm")
    crops_per_frame: int = doc("Random crops drawn from each training frame per epoch.", 4)
    epoch_steps: int = doc("At most this many steps per epoch (a random subset of the epoch's crops); 0: every "
                           "crop.", 0)
    lr_end: float = doc("Learning rate at the last step of the cosine decay.", 5e-6)
    warmup_steps: int = doc("Linear learning-rate warm-up steps from 0.", 50)
    weight_decay: float = doc("Adam(W) decoupled weight decay (toward 0; l2sp pulls toward OIDN instead).", 0.0)
    loss: str = doc("Training loss in OIDN's output space (PU of the exposed radiance, as OIDN's training kit): "
                    "'l1'; 'l1_relative' (each crop's L1 divided by stock OIDN's on it: every crop counts by its "
                    "gain over OIDN); or 'l1_ssim' (0.16 L1 + 0.84 (1 - SSIM), the kit's mix with single-scale SSIM "
                    "for small crops).", "l1")
    l2sp: float = doc("Weight of the L2-SP penalty (Li et al. 2018) that keeps the weights near OIDN's: l2sp x "
                      "the mean over layers of |w - w_oidn|^2 / |w_oidn|^2; 0: none.", 0.0)
    distill: float = doc("Fraction of each batch whose target is stock OIDN's own output on a changed input "
                         "(colours permuted and rescaled, the image at half resolution, noise of another spp), "
                         "so the network keeps what OIDN does on inputs unlike the training set; 0: none.", 0.0)
    diversify: float = doc("Probability that a training crop (with its GT) comes from a changed frame: the light "
                           "tinted (per-channel gains on colour and target alike) and, half the time, the frame at "
                           "half resolution: colours and scales the training scenes lack.", 0.0)
    trainable: str = doc("Which weights train: 'all', 'decoder' (the encoder stays OIDN's), 'bias' (biases "
                         "only: 0.5 % of the weights) or 'fine' (the layers at the fine_levels finest resolutions; "
                         "the coarser ones stay OIDN's: docs/oidn.md, 'Only the fine levels').", "all")
    fine_levels: int = doc("With trainable 'fine': how many of the UNet's five resolutions train, from the full one "
                           "(1: full only, 2: full and half, ... 5: all); 4 keeps only the bottleneck (1/16 "
                           "resolution) OIDN's.", 4)
    augment: bool = doc("OIDN's own augmentation: random colour-channel permutation (colour, albedo and target "
                        "together), normal-channel permutation, flips and transposes.", True)
    blend: float = doc("Weight-space blend with OIDN (WiSE-FT, Wortsman et al. 2022) when the run is used or "
                       "exported: w = w_oidn + blend (w_trained - w_oidn); 1: the trained weights.", 1.0)
    val_frames: int = doc("Validation frames scored after every epoch (each at every sample count of the run); 0: "
                          "the whole val split.", 0)
    target: str = doc("Training target: 'gt_clean' (the cleaned reference, as every denoiser here) or 'gt1' (the "
                      "raw reference, unbiased but noisy); validation scores against GT_clean either way, as make "
                      "eval does.", "gt_clean")

    def check(self, bad: Bad) -> None:
        super().check(bad)
        self.one_of(bad, "target", ("gt_clean", "gt1"))
        if not re.fullmatch(r"rt_hdr(_alb(_nrm)?)?(_small)?|rt_hdr_calb_cnrm(_large)?", self.network):
            bad("network", "expected rt_hdr, rt_hdr_alb or rt_hdr_alb_nrm (optionally _small), rt_hdr_calb_cnrm or "
                           f"rt_hdr_calb_cnrm_large, got {self.network!r}")
        self.at_least(bad, 1, "crops_per_frame")
        if self.crop % 16:
            bad("crop", f"must be a positive multiple of 16 (OIDN's alignment), got {self.crop}")
        self.one_of(bad, "loss", ("l1", "l1_relative", "l1_ssim"))
        self.one_of(bad, "trainable", ("all", "decoder", "bias", "fine"))
        if not 1 <= self.fine_levels <= 5:
            bad("fine_levels", f"expected 1 to 5 (the UNet's resolutions), got {self.fine_levels}")
        if not 0 <= self.distill < 1 or not 0 <= self.diversify <= 1:
            bad("distill/diversify", f"probabilities: distill in [0, 1), diversify in [0, 1]; got {self.distill}, "
                                     f"{self.diversify}")
        self.at_least(bad, 0, "l2sp", "lr_end", "warmup_steps", "epoch_steps")


def weight_problem(weight: float) -> str | None:
    """Why ``weight`` cannot be the temporal filter's weight (``pipeline.temporal.blend_history``), or None: the one
    range and text of every entry point (``eval.temporal_weight``, ``denoise --temporal-weight``)."""
    if 0.0 < weight <= 1.0:
        return None
    return f"expected the new frame's share of the blend, in (0, 1] (1: no history), got {weight}"


@dataclass
class EvalConfig(Section):
    methods: list = doc("Methods to evaluate, in table order: noisy, oidn (colour+albedo+normal), oidn_albedo, "
                        "oidn_color, oidn_prefilter (OIDN's final-frame mode: aux prefiltered, cleanAux), oidn_ft, "
                        "oidn_ft_albedo and oidn_ft_color (OIDN fine-tuned on the store: make "
                        "train MODEL=oidn_ft), isik, "
                        "afgsa, ours (the diffusion denoiser: this config's run, else train/shipped; the table's "
                        "weights column says which), base_only (its base without the Control Module); ours and "
                        "base_only take options after an optional run variant: sN (sampler steps), skipN, kN (mean "
                        "of N samples), noise/render/estimate (start), strengthN, e.g. ours_s3_k4 or ours_large (run "
                        "diffusion_spp<N>_large; see evaluate/methods.py). Any method takes _xN last: its self-ensemble "
                        "over N (2, 4, 8) flipped/transposed copies of the frame at N times its time (oidn_x8, "
                        "ours_x8). A method whose model is missing is listed as not available.",
                        factory=lambda: ["noisy", "oidn", "oidn_x8", "oidn_prefilter", "oidn_albedo", "oidn_color",
                                         "oidn_ft",
                                         "oidn_ft_albedo", "oidn_ft_color", "isik", "afgsa", "ours",
                                         "ours_x8", "ours_s3_k4", "base_only"])
    spp: list = doc("Sample counts of the noisy input; one table each (paper: 4, 16, 64). Counts the store cannot "
                    "pool from its stacks are reported as skipped.", factory=lambda: [4, 16, 64])
    split: str = doc("Store split to evaluate (the stress and external splits are always reported separately).",
                     "test")
    stress: bool = doc("Also report the store's 'stress' split (dataset.stress presets) as its own group, never "
                       "averaged into the split above.", True)
    frames: int = doc("Evaluate at most this many frames of the split (0: all).", 0)
    realizations: int = doc("Noise realizations per frame and spp: every method denoises this many disjoint groups "
                            "of the frame's stacks (at most stacks × stack_spp / spp of them; 1: the first stacks "
                            "only) and the frame's metrics are their mean, so the per-frame numbers carry less of "
                            "one noise draw's luck (one 4-spp realization moves a method's PSNR gain on a frame by "
                            "about 0.1 dB) at that many times the time. Crops show the first realization.", 1)
    metrics: list = doc("Metric columns: l1, psnr, ssim, flip (LDR, on the tonemap), hdr_flip, fvvdp.",
                        factory=lambda: ["l1", "psnr", "ssim", "flip", "hdr_flip", "fvvdp"])
    fvvdp_display: str = doc("FovVideoVDP display model (pyfvvdp's display_models.json).", "standard_4k")
    equal_time: str = doc("Equal-time Monte Carlo: 'render' (render each frame at the equal-time spp with the "
                          "dataset's renderer, cached in the store), 'pool' (average stored stacks, capped at "
                          "stacks x stack_spp), 'none'.", "render")
    equal_time_methods: list = doc("Denoisers whose time budget gets an equal-time MC row.",
                                   factory=lambda: ["ours", "isik", "oidn"])
    equal_time_max_spp: int = doc("Cap of the equal-time MC spp ('render'); capped rows are marked.", 4096)
    device: str = doc("Torch device of the Isik and diffusion methods: 'auto', 'cpu', 'cuda', ...", "auto")
    seed: int = doc("Sampling seed of the diffusion methods.", 0)
    bootstrap_resamples: int = doc("Resamples of the paired bootstrap intervals of the differences between "
                                   "methods (percentile method, 95 %).", 5000)
    bootstrap_seed: int = doc("Seed of the paired bootstrap (numpy default_rng): the same numbers give the same "
                              "intervals.", 0)
    crops: int = doc("Frames in the crop grid per spp.", 4)
    crop_size: int = doc("Side of each crop in pixels.", 64)
    sequence_methods: list = doc("Methods scored along each scene's camera move (the sequence page, scenes of at "
                                 "least two frames): any per-frame method of eval.methods' names, "
                                 "oidn_prefilter_temporal (oidn_prefilter on the diffuse light averaged over "
                                 "eval.temporal_window frames, its output blended with its own warped history: the "
                                 "temporal filter), ours_filter (the same on ours: what denoise --sequence runs for a "
                                 "model that does not read the past) and ours_temporal "
                                 "(ours given its own warped previous output, where the model reads the past: "
                                 "diffusion.history; else the row says it is unavailable). Empty: no sequence page.",
                                 factory=lambda: ["noisy", "oidn_prefilter", "oidn_prefilter_temporal", "ours",
                                                  "ours_filter", "ours_temporal"])
    temporal_weight: float = doc("Share of the new frame in the temporal filter's exponential blend (1: no "
                                 "history); the history is clamped to the new output's 3x3 range. 0.7: the rule "
                                 "of docs/sequences.md on configs/sequence.yaml's val split.", 0.7)
    temporal_window: int = doc("Frames (this one included) over which the temporal methods average the noisy "
                               "diffuse light before denoising, each past frame reprojected and read at the pixel "
                               "its spot falls in; reflections and emission stay this frame's; 1: no averaging. "
                               "8: the rule of docs/sequences.md (\"Read without resampling\") on the val split "
                               "and the val_* scenes. A model that reads the past (diffusion.history) trains on the "
                               "input averaged so.", 8)
    temporal_gate: float = doc("A past frame's diffuse light counts in that average only where it differs from "
                               "this frame's by at most this many standard deviations of the difference (from the "
                               "variance layers); 0: no gate. 2: the rule of docs/sequences.md (\"A gate on the "
                               "averaged light\").", 2.0)
    temporal_ahead: int = doc("Frames after this one that the temporal methods average too, for a sequence on disk "
                              "whole (a shot rendered offline; make eval and denoise --sequence): each reprojected "
                              "with the cameras and depth, or followed forward along the motion vectors (a "
                              "Vector pass's to-next half); the temporal filter then reads both sides (its history the mean "
                              "of the frame before's and of the same filter run backwards from these frames). 0: the "
                              "frames before alone and the causal filter, as frames that arrive one at a time. 7: the "
                              "rules of docs/sequences.md (\"Frames after this one too\", \"The filter on both "
                              "sides\").", 7)
    sequence_fps: float = doc("Frame rate at which FovVideoVDP watches a sequence.", 24.0)
    stability_large: bool = doc("make stability also runs the 1920x1080 case.", True)
    out: str = doc("Report folder; empty: reports/<name of the runs folder>.", "")


    def check(self, bad: Bad) -> None:
        if self.realizations < 1:
            bad("realizations", f"must be >= 1 (the first stacks only), got {self.realizations}")
        if self.bootstrap_resamples < 100:
            bad("bootstrap_resamples", f"must be >= 100 for a 95 % percentile interval, got {self.bootstrap_resamples}")
        self.one_of(bad, "equal_time", ("render", "pool", "none"))
        if (why := weight_problem(self.temporal_weight)) is not None:
            bad("temporal_weight", why)
        if self.temporal_window < 1:
            bad("temporal_window", f"must be >= 1 (1: no averaging), got {self.temporal_window}")
        if self.temporal_ahead < 0:
            bad("temporal_ahead", f"must be >= 0 (0: the frames before alone), got {self.temporal_ahead}")
        if not self.temporal_gate >= 0:
            bad("temporal_gate", f"must be >= 0 (0: no gate), got {self.temporal_gate}")
        if self.sequence_fps <= 0:
            bad("sequence_fps", f"must be > 0, got {self.sequence_fps}")


@dataclass
class Config:
    seed: int = doc("Master seed: scene i is generated from (seed, i); every render seed derives from it.", 0)
    store: str = doc("Path of the EXR buffer store (relative paths are relative to the working directory).", "data/default")
    dataset: DatasetConfig = doc("Dataset stage (make dataset).", factory=DatasetConfig)
    scene: SceneConfig = doc("Scene randomizer.", factory=SceneConfig)
    render: RenderConfig = doc("Renderer and integrator.", factory=RenderConfig)
    executor: ExecutorConfig = doc("Where frames run.", factory=ExecutorConfig)
    runs: str = doc("Folder for checkpoints, loss curves and logs of the training stages; empty: runs/<the store's "
                    "folder name> (data/tiny: runs/tiny), so two configs with their own stores never share runs.", "")
    clean: CleanConfig = doc("GT cleaner (make gt-clean) and the Isik baseline (make train MODEL=isik).",
                             factory=CleanConfig)
    afgsa: AfgsaConfig = doc("AFGSA, the paper's third competitor (make train MODEL=afgsa SPP=4).",
                             factory=AfgsaConfig)
    diffusion: DiffusionConfig = doc("Diffusion denoiser: frozen base + Control Module (make train SPP=4).",
                                     factory=DiffusionConfig)
    oidn: OidnConfig = doc("Where OIDN's weights come from.", factory=OidnConfig)
    oidn_ft: OidnFtConfig = doc("OIDN fine-tuned on the store (make train MODEL=oidn_ft SPP=any).",
                                factory=OidnFtConfig)
    eval: EvalConfig = doc("Evaluation (make eval, make stability).", factory=EvalConfig)


# --------------------------------------------------------------------------------------------
# Loading


_FLOAT_TEXT = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")


def _check_type(value: Any, tp: Any, where: str) -> Any:
    """Validate (and gently coerce int → float) a YAML value against a field's annotation."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in args:
        inner = [a for a in args if a is not type(None)]
        return None if value is None else _check_type(value, inner[0], where)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {type(value).__name__}")
        return _from_dict(tp, value, where)
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp is float and isinstance(value, str) and _FLOAT_TEXT.fullmatch(value.strip()):
        return float(value)   # YAML 1.1 reads "1e-4" (no dot) as a string; users mean the number
    if tp in (int, float) and isinstance(value, bool):
        raise ConfigError(f"{where}: expected {tp.__name__}, got a boolean")
    if tp in (int, float, str, bool, list, dict) and not isinstance(value, tp):
        raise ConfigError(f"{where}: expected {tp.__name__}, got {type(value).__name__} {value!r}")
    return value


def _from_dict(cls: type, data: dict, where: str) -> Any:
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        prefix = f"{where}." if where else ""
        raise ConfigError(f"unknown config key {prefix}{unknown[0]!s} (known: {', '.join(sorted(names))})")
    kwargs = {}
    for key, value in data.items():
        kwargs[key] = _check_type(value, hints[key], f"{where}.{key}" if where else key)
    return cls(**kwargs)


def yaml_problem(exc: yaml.YAMLError) -> str:
    """PyYAML's error in one line: where (line, column) and what, without its multi-line excerpt of the text."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    what = " ".join(str(getattr(exc, "problem", None) or exc).split())
    return f"line {mark.line + 1}, column {mark.column + 1}: {what}" if mark is not None else what


def parse_override(text: str) -> tuple[list[str], Any]:
    """``dataset.scenes=4`` → (["dataset", "scenes"], 4); the value is parsed as YAML."""
    if "=" not in text:
        raise ConfigError(f"override {text!r}: expected key=value")
    key, raw = text.split("=", 1)
    if not key or any(not part for part in key.split(".")):
        raise ConfigError(f"override {text!r}: empty key")
    try:
        value = yaml.safe_load(raw) if raw != "" else ""
    except yaml.YAMLError as exc:
        raise ConfigError(f"override {text!r}: value is not valid YAML ({yaml_problem(exc)})") from None
    return key.split("."), value


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    for text in overrides:
        path, value = parse_override(text)
        node = data
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {text!r}: {part} is not a section")
        node[path[-1]] = value
    return data


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Load ``path`` (or the built-in defaults) and apply ``key=value`` overrides."""
    data: dict = {}
    source = "<defaults>"
    if path is not None:
        source = str(path)
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read config ({exc.strerror})") from exc
        try:
            data = yaml.safe_load(text) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML ({yaml_problem(exc)})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a mapping at the top level")
    apply_overrides(data, list(overrides or []))
    try:
        cfg = _from_dict(Config, data, "")
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    validate(cfg, source)
    if not cfg.runs:
        cfg.runs = str(Path("runs") / (Path(cfg.store).name or "default"))
    return cfg


def validate(cfg: Config, source: str) -> None:
    """Value checks that types alone cannot express: every section's ``check``, its keys named
    ``<source>: <section>.<key>``. No rule spans two sections."""
    for f in dataclasses.fields(cfg):
        section = getattr(cfg, f.name)
        if isinstance(section, Section):
            try:
                section.check(_bad_in(source, f.name))
            except TypeError as exc:     # a value of a type its rule cannot compare (a list item a mapping, ...)
                raise ConfigError(f"{source}: {f.name}: a value of the wrong type ({exc})") from None


def _bad_in(source: str, section: str) -> Bad:
    def bad(key: str, msg: str) -> NoReturn:
        raise ConfigError(f"{source}: {section}.{key}: {msg}")
    return bad


def to_dict(cfg: Any) -> dict:
    return dataclasses.asdict(cfg)


def documentation(cls: type = Config, prefix: str = "") -> list[tuple[str, str, str]]:
    """(dotted key, default, doc) for every leaf key, in declaration order."""
    rows = []
    for f in dataclasses.fields(cls):
        key = f"{prefix}{f.name}"
        hint = typing.get_type_hints(cls)[f.name]
        if dataclasses.is_dataclass(hint):
            rows.extend(documentation(hint, key + "."))
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        rows.append((key, yaml.safe_dump(default, default_flow_style=True).strip().removesuffix("..."
                                                                                       ).strip(), f.metadata["doc"]))
    return rows


def documentation_markdown() -> str:
    lines = [
        "# Configuration keys",
        "",
        "Generated by `python -m pipeline config --doc` from the dataclasses in `pipeline/config.py`;",
        "a test fails when this file and the code disagree. Every key can be set in a YAML file",
        "(`--config FILE`, `make ... CONFIG=FILE`) or on the command line as `key=value`",
        "(`python -m pipeline dataset dataset.scenes=4`, `make dataset dataset.scenes=4`).",
        "",
        "| key | default | meaning |",
        "| --- | --- | --- |",
    ]
    for key, default, text in documentation():
        lines.append(f"| `{key}` | `{default}` | {text} |")
    return "\n".join(lines) + "\n"


# ---- Runs: the folder each model writes under runs, and the device it runs on --------------------
# Training runs: the folder each model writes under ``cfg.runs``, and the device it runs on.
#
# One folder per model and sample count (``spp<N>``, or ``sppany`` for one model serving every count):
#
# - ``cleaner``: ``<runs>/cleaner``;
# - ``isik`` (the Isik baseline): ``<runs>/isik_spp<N>``;
# - ``afgsa``: ``<runs>/afgsa_spp<N>``; trained against another target than gt_clean
#   (``afgsa.target``): ``<runs>/afgsa_<target>_spp<N>``;
# - ``oidn_ft`` (OIDN fine-tuned, one model for every spp): ``<runs>/oidn_ft_<network>``
#   (``oidn_ft.network``, or the network given as ``variant``);
# - ``diffusion``: ``<runs>/diffusion_spp<N>``, with ``_<variant>`` (``diffusion.name``, or the
#   variant given) appended.
#
# ``find_run``: the run that serves a sample count, its own (``spp<N>``) else the one for every
# count (``sppany``); the evaluator, ``denoise`` and the reports find Isik, AFGSA and diffusion runs by it.
#
# Importing this module does not import torch; ``pick_device`` does.
MODELS = ("cleaner", "isik", "afgsa", "oidn_ft", "diffusion")


def spp_tag(spp: int | str) -> str:
    """``spp4``, ``spp16``, ..., or ``sppany``."""
    return "sppany" if str(spp) == "any" else f"spp{int(spp)}"


def run_dir(cfg: Config, model: str, spp: int | str | None = None, variant: str | None = None) -> Path:
    """The run folder of ``model`` (one of ``MODELS``) at ``spp``; ``variant``: for diffusion the run
    variant (default: ``diffusion.name``), for oidn_ft the network (default: ``oidn_ft.network``)."""
    runs = Path(cfg.runs)
    if model == "cleaner":
        return runs / "cleaner"
    if model == "isik":
        return runs / f"isik_{spp_tag(spp)}"
    if model == "afgsa":
        target = "" if cfg.afgsa.target == "gt_clean" else f"_{cfg.afgsa.target}"
        return runs / f"afgsa{target}_{spp_tag(spp)}"
    if model == "oidn_ft":
        return runs / f"oidn_ft_{variant or cfg.oidn_ft.network}"
    if model == "diffusion":
        variant = cfg.diffusion.name if variant is None else variant
        return runs / (f"diffusion_{spp_tag(spp)}" + (f"_{variant}" if variant else ""))
    raise ValueError(f"model must be one of {', '.join(MODELS)}, got {model!r}")


def run_candidates(cfg: Config, model: str, spp: int | str, variant: str | None = None) -> list[Path]:
    """Where the run of ``model`` that serves ``spp`` may be, in order: its own (``<model>_spp<N>``), then
    the one model for every sample count (``<model>_sppany``); for ``spp`` 'any' only that one."""
    own = run_dir(cfg, model, spp, variant)
    return [own] if str(spp) == "any" else [own, run_dir(cfg, model, "any", variant)]


def find_run(cfg: Config, model: str, spp: int | str, weights: str, variant: str | None = None,
             serves: Callable[[Path], bool] | None = None, fallback: Path | None = None) -> Path | None:
    """The run of ``model`` that serves ``spp``: the first of ``run_candidates`` with ``weights`` (a file name)
    in it, the any-spp run only where ``serves(folder)`` says it trained on ``spp`` (default: it serves
    every count), else ``fallback`` when it has ``weights``; None if none does."""
    own, *others = run_candidates(cfg, model, spp, variant)
    if (own / weights).exists():
        return own
    for folder in others:
        if (folder / weights).exists() and (serves is None or serves(folder)):
            return folder
    if fallback is not None and (fallback / weights).exists():
        return fallback
    return None


def pick_device(name: str):
    """The torch device of a ``*.device`` config key: 'auto' is CUDA where available, else the CPU."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)
