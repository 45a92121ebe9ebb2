"""Stage 2: the GT cleaner, an Isik et al. 2021 affinity network that turns GT1/GT2 into GT_clean
(paper section 3.1, eqs. 1-3), and the same network trained as the Isik baseline denoiser.

- ``clean.model``: the network (per-pixel embedding → U-Net → K dilated affinity kernels that
  filter the HDR radiance); ``load_model`` reads a checkpoint.
- ``clean.data``: network inputs from store buffers (channel list derived from the schema),
  crops/flips, the cleaner and baseline training pairs.
- ``clean.losses``: SMAPE (paper eq. 2, defined once in ``pipeline.metrics``).
- ``clean.train``: ``train(cfg, mode="cleaner" | "baseline", spp)``: AdamW, validation each
  epoch, best + last checkpoints in safetensors, exact resume, loss curve.
- ``clean.apply``: ``apply_cleaner(cfg)`` writes ``gt_clean.exr`` for every frame (idempotent,
  keyed by the checkpoint's SHA-256); ``denoise`` runs a model on one frame.
- ``clean.cli``: ``cmd_gt_clean`` and ``cmd_train_isik`` for ``python -m pipeline``.
"""
