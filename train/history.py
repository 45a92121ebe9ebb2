"""What a model that reads the past (``diffusion.history``) trains on: frame t's input as the temporal methods
serve it, and the history beside it.

- **The input**: frame t's noisy diffuse light averaged over it, the frames before it and those after it as
  ``pipeline.temporal.InputWindow`` averages it at inference (``eval.temporal_window`` frames, gated at
  ``eval.temporal_gate``, ``eval.temporal_ahead`` frames after; 1 frame and none after: the frame's own
  input), so the model trains on the input ``denoise --sequence`` and the sequence evaluation give it.
- **The history**: an output of frame t−1, brought into frame t (``pipeline.motion``: the noisy input's own depth
  and normal and the two cameras, as a user's renderer would give them) with its validity mask;
  ``train.model.inputs`` encodes it. In training that output is **OIDN's final-frame output** of frame t−1's
  input (averaged as above, the same stacks as frame t's), computed once when the pack is built. Why not the
  model's own output: that output depends on the weights being trained, so it would have to be recomputed every
  epoch (or the training unrolled over frames), and the pack could not be shared by runs; OIDN's output does not
  change, costs one OIDN pass per pack variant (``train.data.PACK_VARIANTS``: a (spp, stacks) input of the
  frame, up to 4 per frame), and is what the model's output starts from (the Control Module corrects OIDN's
  estimate), so at inference, fed its own output, the model gets a history at least as good as the one it
  trained on. A frame without a previous frame (t = 0) gets no history: its history channels and
  ``has.history`` are zero.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from mcdenoise.pipeline import motion, temporal

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


@dataclass
class _Walk:
    """One stack selection's way along a scene: the window, the last frame taken, its averaged input and view."""
    scene: str
    window: temporal.InputWindow
    frame: int = -1
    averaged: dict | None = None
    view: motion.View | None = None
    ahead: dict = field(default_factory=dict)      # {frame: (its buffers, its view)}, read ahead


class SequenceInputs:
    """Frames of a store as a model that reads the past trains on them (the module docstring): ``of(key, stacks,
    read)`` is frame ``key``'s input on ``stacks`` averaged over the window, with the history of its previous
    frame. Each stack selection walks its scene's frames in order, so a pack of consecutive frames averages each
    frame once; a frame asked out of order starts a new walk from the window's first frame."""

    def __init__(self, store: Store, window: int = 1, gate: float | None = None, ahead: int = 0):
        self.store, self.window, self.gate, self.ahead = store, int(window), gate, int(ahead)
        self.walks: dict[tuple, _Walk] = {}

    def of(self, key: FrameKey, stacks: tuple, read: Callable[[int], dict]) -> dict[str, np.ndarray]:
        """``stacks``: the stack selection (any hashable that names it); ``read(frame)``: the buffers of
        ``key.scene``'s ``frame`` on it."""
        walk = self.walks.get(stacks)
        if walk is None or walk.scene != key.scene or walk.frame != key.frame - 1:
            walk = self.walks[stacks] = _Walk(key.scene, temporal.InputWindow(self.window, gate=self.gate,
                                                                              ahead=self.ahead))
            for f in range(self._first(key), key.frame):        # the window of frame t - 1: frames t - W .. t - 1
                self._take(walk, f, read)
        before, before_view, had = walk.averaged, walk.view, walk.frame == key.frame - 1
        self._take(walk, key.frame, read)
        history = (motion.warp_previous(oidn_output(before), walk.view, before_view)
                   if had and motion.linked(walk.view, before_view) else None)
        return with_history(walk.averaged, history)

    def _first(self, key: FrameKey) -> int:
        """The earliest frame of the run of rendered frames just before ``key`` within the window of frame t − 1."""
        first = key.frame
        while first > max(0, key.frame - self.window) and self.store.frame_record(key.scene, first - 1) is not None:
            first -= 1
        return first

    def _take(self, walk: _Walk, frame: int, read: Callable[[int], dict]) -> None:
        """Frame ``frame`` into the walk, with the rendered frames right after it (each read once: kept until
        its own turn)."""
        buffers, walk.view = walk.ahead.pop(frame, None) or self._read(walk.scene, frame, read)
        walk.ahead = {f: v for f, v in walk.ahead.items() if f > frame}
        upcoming = []
        for f in range(frame + 1, frame + 1 + self.ahead):
            if f not in walk.ahead:
                if self.store.frame_record(walk.scene, f) is None:
                    break
                walk.ahead[f] = self._read(walk.scene, f, read)
            later, view = walk.ahead[f]
            upcoming.append((walk.window.keep(later), view))
        walk.averaged, walk.frame = walk.window.take(buffers, walk.view, upcoming), frame

    def _read(self, scene: str, frame: int, read: Callable[[int], dict]) -> tuple[dict, motion.View]:
        buffers = read(frame)
        return buffers, motion.View.of(self.store.camera(scene, frame), buffers)
