"""The trained competitors of the denoiser, each a module of its own, sharing plain helpers with it (its data
transforms and OIDN's network), never its training loop:

- ``train.baselines.oidn_ft``: OIDN's own network fine-tuned from its weights on the store (augmentation, L2-SP,
  distillation, trainable subsets, WiSE-FT blend), exported as a ``.tza`` OIDN itself loads;
- ``train.baselines.afgsa``: AFGSA (Yu et al. 2021), an auxiliary-feature-guided self-attention denoiser trained with a
  patch critic; ``train.baselines.afgsa_report``: AFGSA against GT_clean vs against GT1.

The Isik baseline stays with the cleaner (``clean.model``): it is the cleaner's network on noisy input.
"""
