"""Stage 3: the denoiser, a Control Module on OIDN's frozen network (paper Fig. 1), read like OIDN's training
kit: one flat module per concern.

- ``train.model``: the network: OIDN's UNet and its HDR processing in PyTorch, its aux prefilter, the network's
  input (OIDN's, and the condition of every other buffer), the Control Module on the frozen base
  (``ControlledOIDN``), where models are (``find_run``, ``SHIPPED_MODEL``), save and load.
- ``train.oidn``: OIDN, the library (``pyoidn``): the call every stage uses, and its built-in weights.
- ``train.data``: training packs (the store decoded once) and augmented crops, the run's frames
  (``StoreSource``), ``pack``.
- ``train.history``: the past a model that reads history is given: the previous output warped into this
  frame (``diffusion.history``; in training OIDN's output of the frame before).
- ``train.loss``: each crop's error relative to OIDN's.
- ``train.sampler``: what is diffused and predicted (``Formulation``: the residual around OIDN's output, x0,
  the schedule), the timesteps training draws, the min-SNR weight; the reverse diffusion and the strength knob.
- ``train.train``: ``make train``: the training script, its loop written out (data, model, loss, optimiser
  step, EMA, validation, checkpoint); DDP under torchrun.
- ``train.infer``: inference: ``denoise`` (a store frame or an EXR, with ours or OIDN itself), the
  self-ensemble, σ's calibration.
- ``train.sequence``: ``denoise --sequence``: a rendered sequence, each frame blended with its warped
  history (``pipeline.temporal``'s filter, the motion from the EXR headers' cameras and depth).
- ``train.export``: a self-contained model folder (``train/shipped``) and changes to one after training;
  an oidn_ft run as a ``.tza`` OIDN loads.
- ``train.bench``: ``bench-denoise``: seconds per frame of ours, its base and OIDN.
- ``train.baselines``: the trained competitors, apart from the denoiser: ``train.baselines.oidn_ft`` (OIDN's
  network fine-tuned from its weights, exported for OIDN itself), ``train.baselines.afgsa`` (AFGSA, Yu et al. 2021)
  and ``train.baselines.afgsa_report`` (AFGSA against GT_clean vs against GT1).
"""
