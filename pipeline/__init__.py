"""mcdenoise pipeline, the core: what every stage shares, and the command line.

No module of the core imports a stage (render, clean, train, evaluate) except the command line
(``pipeline.__main__``), which dispatches to them (tests/test_architecture.py checks it). Stages
exchange data through the store and the config defined here. Importing this package is cheap:
Mitsuba and torch load on demand.

- ``pipeline.__main__``: ``python -m pipeline <stage>``: builds the parser from every package's
  ``commands`` module, parses the flags, dispatches.
- ``pipeline.commands``: the options the stages' subcommands share (``--config``, ``key=value``,
  ``--quiet``, ``--spp``) and the core's own subcommands (``inspect``, ``config``, ``verify``).
- ``pipeline.config``: the typed config (YAML → dataclasses, ``key=value`` overrides, validation).
- ``pipeline.errors``: the errors a user can act on, under ``PipelineError``.
- ``pipeline.schema``: every buffer the renderer produces, its EXR channels and storage type.
- ``pipeline.exr``: one multi-channel EXR image of the store, written atomically.
- ``pipeline.foreign_layers``: where other tools (Mitsuba's aov integrator, Blender) put colour, albedo, normal.
- ``pipeline.store``: the on-disk store (manifests, frames, stacks): the one reader/writer API.
- ``pipeline.inspect``: ``inspect``: what a store holds, from its manifests and headers.
- ``pipeline.verify``: ``verify``: check every file of a store.
- ``pipeline.executors``: where frame tasks run: worker processes or Ray.
- ``pipeline.mitsuba_env``: import Mitsuba safely (LLVM first, then the variant).
- ``pipeline.numerics``: non-finite repair, constant detection, the variance of a pixel mean.
- ``pipeline.noise``: is an image's noise independent from pixel to pixel (``denoise --exr``'s check).
- ``pipeline.color``: the tonemaps (Reinhard, log, gamma) and their inverses, numpy and torch alike.
- ``pipeline.metrics``: the image metrics shared by training and evaluation.
- ``pipeline.features``: how every network's input channels encode the buffers, in one table.
- ``pipeline.fit``: the training loop every trainer runs (resume, best/last checkpoint, time budget).
- ``pipeline.checkpoint``: safetensors checkpoints (the resumable state) and training curves.
- ``pipeline.weights``: trained models on disk: format tags, save, load, the checks of what they were built on.
- ``pipeline.runs``: the run folder of each model, and the device it runs on.
- ``pipeline.oidn``: Intel Open Image Denoise, the one call every stage uses (its own or given weights).
- ``pipeline.oidn_net``: OIDN's network in PyTorch, equal to pyoidn's output (what trains).
- ``pipeline.oidn_weights``: OIDN's trained weights, from pyoidn's library or a ``.tza`` file.
- ``pipeline.tza``: OIDN's Tensor Archive format, read and written.
- ``pipeline.ensemble``: a denoiser's self-ensemble over flipped and transposed copies of a frame.
- ``pipeline.figures``: the crop grid the reports share.
- ``pipeline.progress``, ``pipeline.timing``, ``pipeline.versions``: progress bars, wall-clock
  timing for the benchmarks, package versions and the machine for provenance.
"""
__version__ = "0.1.0"
