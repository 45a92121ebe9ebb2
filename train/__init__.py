"""Stage 3: the diffusion denoiser, a pixel-space diffusion base (DeepFloyd IF stage II's layout)
with a trainable Control Module (paper Fig. 1).

- ``train.base``: the base UNet (load, build, the stand-in in ``train/base_model_paper``);
  ``train.pretrain``: trains a stand-in base (``make pretrain``).
- ``train.control``: the Control Module and the controlled denoiser around the base.
- ``train.diffusion`` / ``train.formulation``: the diffusion process, what is diffused and
  predicted, the loss weighting; ``train.sampler``: the reverse diffusion.
- ``train.data``, ``train.pack``, ``train.estimate``: model inputs, training packs, first estimates.
- ``train.train``: the training loop (``fit``); ``train.model``: assemble, save and load a run.
- ``train.infer``: denoise a frame with a trained run; ``train.export``: a self-contained model folder.
- ``train.cli``, ``train.bench``, ``train.gpu_recipe``: ``python -m pipeline`` entry points,
  inference timing, the GPU recipe.
"""
