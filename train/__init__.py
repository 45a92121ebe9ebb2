"""Stage 3: the diffusion denoiser, a Control Module on OIDN's frozen network (paper Fig. 1), and the
other trained competitors: ``oidn_ft``, OIDN's own network fine-tuned on the store, and AFGSA.

The diffusion denoiser, by role (``make train SPP=N`` → ``commands._train`` → ``train.train``):

- ``train.model``: the network (OIDN's frozen base + the Control Module, ``ControlledOIDN``), where
  models are (``run_dir``, ``find_run``, ``SHIPPED_MODEL``), save and load.
- ``train.formulation``: what is diffused and predicted (the residual around OIDN's output, x0, the
  schedule), the timesteps training draws, the min-SNR weight.
- ``train.loss``: each crop's error relative to OIDN's.
- ``train.sampler``: the reverse diffusion and the strength knob.
- ``train.data``: the inputs in OIDN's space, training packs and crops, the run's frame sources.
- ``train.train``: the training run, written out in order (``train``: model, data, optimiser; the
  epochs and the step; validation, the files) and its learning-rate schedule, EMA and DDP helpers.
- ``train.infer``: denoise a frame with a model folder (``load_denoiser``), σ's calibration.
- ``train.export``: a self-contained model folder (``train/shipped``) and changes to one after training.

The others: ``train.baselines.oidn_ft`` (OIDN's network fine-tuned from its pretrained weights: augmentation,
L2-SP, distillation, trainable subsets, WiSE-FT blend, exported for OIDN itself); ``train.baselines.afgsa``
(AFGSA, Yu et al. 2021) and ``train.baselines.afgsa_report``. ``train.cli`` (``denoise``, ``pack``),
``train.bench``, ``train.gpu_recipe`` and ``train.commands`` (the subcommands ``train``, ``export``,
``gpu-prepare``, ``gpu-recipe``, ``pack``, ``denoise``, ``afgsa-report``, ``bench-denoise``).
"""
