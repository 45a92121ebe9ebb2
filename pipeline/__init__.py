"""mcdenoise pipeline, the core: what every stage shares, and the command line.

No module of the core imports a stage (render, clean, train, evaluate) except the command line
(``pipeline.cli``), which dispatches to them (tests/test_architecture.py checks it). Stages exchange
data through the store and the config defined here. Importing this package is cheap: Mitsuba and
torch load on demand.

- ``pipeline.cli``: ``python -m pipeline <stage>``: every subcommand's flags and the one call it makes
  (``pipeline.__main__`` runs it).
- ``pipeline.config``: the typed config (YAML → dataclasses, ``key=value`` overrides, validation), and
  where each model's run folder is.
- ``pipeline.errors``: the errors a user can act on, under ``PipelineError``.
- ``pipeline.schema``: every buffer the renderer produces, its EXR channels and storage type, and how
  every network's input channels encode the buffers, in one table.
- ``pipeline.exr``: one multi-channel EXR image of the store, written atomically; other tools' layer
  names (Mitsuba's aov integrator, Blender) for colour, albedo and normal.
- ``pipeline.store``: the on-disk store (manifests, frames, stacks): the one reader/writer API.
- ``pipeline.motion``: a frame's camera (from frame.json or an EXR header), projection, and the
  reprojection and warping of one frame onto the next.
- ``pipeline.temporal``: along a sequence: the classic temporal filter (a per-frame output blended with
  its warped, clamped history) and the temporal instability metric.
- ``pipeline.weights``: weight files: OIDN's Tensor Archive (TZA), safetensors with a CRC-32, and model
  folders (format tags, save, load, the checks of what they were built on).
- ``pipeline.checkpoint``: a training run's resumable state (``last.safetensors``).
- ``pipeline.inspect``: ``inspect``: what a store holds, from its manifests and headers.
- ``pipeline.verify``: ``verify``: check every file of a store.
- ``pipeline.executors``: where frame tasks run: worker processes or Ray.
- ``pipeline.mitsuba_env``: import Mitsuba safely (LLVM first, then the variant).
- ``pipeline.numerics``: non-finite repair, constant detection, the variance of a pixel mean.
- ``pipeline.metrics``: the tonemaps (Reinhard, log, gamma) with their inverses, and the image metrics
  shared by training and evaluation.
- ``pipeline.figures``: the crop grid the reports share, training curves, a sequence's animated strip.
- ``pipeline.progress``, ``pipeline.timing``, ``pipeline.versions``: progress bars, wall-clock
  timing for the benchmarks, package versions and the machine for provenance.
"""
__version__ = "0.1.0"
