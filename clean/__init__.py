"""Stage 2: the GT cleaner, an Isik et al. 2021 affinity network that turns GT1/GT2 into GT_clean
(paper section 3.1, eqs. 1-3); the same network trained as the Isik baseline denoiser; and AFGSA,
the paper's third competitor, trained by the same loop on the same inputs.

- ``clean.model``: the affinity network (per-pixel embedding → U-Net → K dilated affinity kernels
  that filter the HDR radiance); ``load_model`` reads a checkpoint of it or of AFGSA.
- ``clean.afgsa``: AFGSA (Yu et al. 2021): block-wise self-attention guided by the auxiliary
  buffers, predicting log radiance, and the patch critic of its adversarial loss.
- ``clean.data``: network inputs from store buffers (channel list derived from the schema),
  crops/flips, the cleaner's and the baselines' training pairs.
- ``clean.losses``: the trainers' losses: SMAPE (paper eq. 2) and L1 from ``pipeline.metrics``,
  and AFGSA's WGAN-GP critic and generator losses in log1p space.
- ``clean.train``: ``train(cfg, mode="cleaner" | "baseline" | "afgsa", spp)``: one loop
  (``pipeline.fit``) for the three recipes, validation each epoch, best + last checkpoints in
  safetensors, exact resume, loss curve.
- ``clean.apply``: ``apply_cleaner(cfg)`` writes ``gt_clean.exr`` for every frame (idempotent,
  keyed by the checkpoint's SHA-256); ``denoise`` runs a model on one frame, tiled.
- ``clean.report``: ``clean-report``: is GT_clean closer to an independent GT2 than GT1 is (and the
  Isik baseline against GT_clean with ``--spp``).
- ``clean.afgsa_report``: ``afgsa-report``: AFGSA trained against GT_clean vs against GT1.
- ``clean.cli``: ``cmd_gt_clean``, ``cmd_train_isik`` and ``cmd_train_afgsa`` for ``python -m pipeline``.
"""
