"""The past a model that reads history (``diffusion.history``) is given: for frame t of a scene, an output of
frame t−1 brought into frame t (``pipeline.motion``: the noisy input's own depth and normal and the two
cameras, as a user's renderer would give them) with its validity mask; ``train.model.inputs`` encodes it.

In training the previous output is **OIDN's final-frame output** of frame t−1 (the same stacks as frame t's
input), computed once when the pack is built. Why not the model's own output: that output depends on the
weights being trained, so it would have to be recomputed every epoch (or the training unrolled over frames),
and the pack could not be shared by runs; OIDN's output does not change, costs one OIDN pass per pack variant
(``train.data.PACK_VARIANTS``: a (spp, stacks) input of the frame, up to 4 per frame) and two camera reads
each, and is what the model's output starts from (the Control Module corrects OIDN's estimate), so at
inference, fed its own output, the model gets a history at least as good as the one it trained on. A frame without a previous
frame (t = 0) gets no history: its history channels and ``has.history`` are zero.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from mcdenoise.pipeline import motion

if TYPE_CHECKING:
    from mcdenoise.pipeline.store import FrameKey, Store


def previous_frames(keys: list[FrameKey]) -> dict[FrameKey, FrameKey]:
    """{key: its previous frame (``FrameKey.previous``)} for the keys whose previous frame is among ``keys`` too,
    in the order of ``keys``."""
    have = set(keys)
    return {k: p for k in keys if (p := k.previous()) in have}


def with_history(buffers: dict[str, np.ndarray], history: tuple[np.ndarray, np.ndarray] | None) -> dict:
    """``buffers`` with ``history`` = (warped previous output, validity) as the ``history`` group's buffers;
    unchanged for None (no history: the group is absent)."""
    if history is None:
        return buffers
    warped, valid = history
    return {**buffers, "history": np.asarray(warped, np.float32), "history_valid": np.asarray(valid, np.float32)}


def oidn_output(buffers: dict[str, np.ndarray]) -> np.ndarray:
    """OIDN's final-frame output (albedo and normal prefiltered): the training history's previous output."""
    from . import oidn
    return oidn.denoise({k: buffers[k] for k in ("color", "albedo", "normal")}, aux=True, clean_aux=True)


def store_history(store: Store, key: FrameKey, prev: FrameKey, buffers: dict, buffers_prev: dict
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The training history of ``key``: OIDN's output of ``prev`` (read as ``buffers_prev``) warped into it with
    both frames' noisy depth and normal (``motion.warp_previous``)."""
    return motion.warp_previous(oidn_output(buffers_prev), motion.View.of(store.camera(key.scene, key.frame), buffers),
                                motion.View.of(store.camera(prev.scene, prev.frame), buffers_prev))
