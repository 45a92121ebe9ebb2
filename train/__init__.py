"""Stage 3: the diffusion denoiser, a pixel-space diffusion base (DeepFloyd IF stage II's layout, or
OIDN's network) with a trainable Control Module (paper Fig. 1); and the other trained competitors:
``oidn_ft``, OIDN's own network fine-tuned on the store, and AFGSA.

- ``train.base``: the base UNet (load, build, the stand-in in ``train/base_model_paper``);
  ``train.pretrain``: a stand-in base's training run (``PretrainTask``, ``make pretrain``).
- ``train.control``: the Control Module and the controlled denoiser around the base.
- ``train.diffusion`` / ``train.formulation``: the diffusion process, what is diffused and
  predicted, the loss weighting; ``train.sampler``: the reverse diffusion.
- ``train.data``, ``train.pack``, ``train.estimate``: model inputs, training packs, first estimates.
- ``train.train``: the diffusion denoiser's training run on the IF-II-layout base (``ControlTask``, a
  ``pipeline.fit`` task reading top to bottom: model, data, optimiser; the step; validation), and
  what every diffusion run shares (learning-rate schedule, EMA, DDP helpers).
- ``train.model``: assemble, save and load a run.
- ``train.infer``: denoise a frame with a trained run; ``train.export``: a self-contained model folder.
- ``train.oidn_ft``: OIDN's network fine-tuned from its pretrained weights (augmentation, L2-SP,
  distillation, trainable subsets, WiSE-FT blend), resumable, exported for OIDN itself.
- ``train.oidn_control``: the diffusion denoiser on OIDN's frozen network, with a Control Module
  copied from its encoder (``ControlledOIDN``: at initialisation exactly OIDN's output).
- ``train.oidn_pack``: what the OIDN-based denoiser reads (every buffer in OIDN's space, with
  buffer-group dropout) and its training pack of augmented crops.
- ``train.oidn_refine``: the OIDN-based denoiser's training run (``RefineTask``, loss relative to
  OIDN), sampler and denoiser (``diffusion.base: oidn``).
- ``train.afgsa``: AFGSA (Yu et al. 2021): block-wise self-attention guided by the auxiliary
  buffers, predicting log radiance, the patch critic and WGAN-GP losses of its adversarial training,
  its recipe on ``clean.train``'s loop and its checkpoint loader; ``train.afgsa_report``:
  ``afgsa-report``: AFGSA trained against GT_clean vs against GT1.
- ``train.cli``, ``train.bench``, ``train.gpu_recipe``: the diffusion stage's command-line entry
  points, inference timing, the GPU recipe (``gpu-prepare`` here, ``gpu-recipe`` on a GPU machine).
- ``train.commands``: the subcommands ``train`` (every model, Isik's through ``clean.cli``),
  ``pretrain``, ``export``, ``gpu-prepare``, ``gpu-recipe``, ``pack``, ``denoise``, ``afgsa-report``
  and ``bench-denoise`` of ``python -m pipeline``.
"""
