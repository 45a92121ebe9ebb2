"""Stage 1: scene randomizer, split-buffer Mitsuba integrator, the frame renderer, and the dataset
stage around them: ``render.dataset`` (plan scenes and frames, run the missing ones, write the
manifests), ``render.external`` (a user's Mitsuba scene into the store), ``render.plan`` (what a
dataset costs) and ``render.bench`` (``make bench``). ``python -m pipeline`` dispatches to them."""
