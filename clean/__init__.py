"""Stage 2: the GT cleaner, an Isik et al. 2021 affinity network that turns GT1/GT2 into GT_clean
(paper section 3.1, eqs. 1-3); and the same network trained as the Isik baseline denoiser.

- ``clean.model``: the affinity network (per-pixel embedding → U-Net → K dilated affinity kernels
  that filter the HDR radiance); ``load_model`` reads a checkpoint of it (or of another network).
- ``clean.data``: network inputs from store buffers (channel list derived from the schema),
  crops/flips, the cleaner's and the baselines' training pairs.
- ``clean.losses``: the trainers' losses: SMAPE (paper eq. 2) and L1 from ``pipeline.metrics``.
- ``clean.train``: ``train(cfg, mode="cleaner" | "baseline", spp)``: one loop (``clean.fit``)
  for any ``Recipe`` (``train_recipe``), validation each epoch, best + last checkpoints in
  safetensors, exact resume, loss curve; ``gt_clean``: what ``gt-clean`` runs (train, then apply).
- ``clean.fit``: the epoch loop the cleaner, the Isik baseline and the trained baselines share (resume,
  best/last checkpoint, time budget, the non-finite step guard).
- ``clean.apply``: ``apply_cleaner(cfg)`` writes ``gt_clean.exr`` for every frame (idempotent,
  keyed by the checkpoint's SHA-256); ``denoise`` runs a model on one frame, tiled.
- ``clean.report``: ``clean-report``: is GT_clean closer to an independent GT2 than GT1 is (and the
  Isik baseline against GT_clean with ``--spp``).
"""
