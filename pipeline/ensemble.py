"""Self-ensembling over the dihedral group: a denoiser run on flipped and transposed copies of a frame,
each output turned back and the outputs averaged (Lim et al. 2017's "geometric self-ensemble").

A CNN denoiser is not equivariant to flips and transposes, so its errors on the eight copies of a
frame are partly independent and their mean has less of them; the image itself is unchanged by the
round trip (``invert(apply(x, t), t) == x``, tested). Every buffer moves with the pixels and vectors
are not turned: OIDN's training augmentation flips and transposes normals the same way, so each copy
is an input the network has seen the like of. The cost is ``n`` runs of the denoiser.

    ensemble(fn, buffers, n)    the mean of fn(buffers) over the first n of TRANSFORMS (1, 2, 4 or 8)
"""
from __future__ import annotations

from typing import Callable

import numpy as np

# (transpose, flip rows, flip columns): the identity first, then the transforms that add most to it.
TRANSFORMS = ((False, False, False), (False, False, True), (False, True, False), (False, True, True),
              (True, False, False), (True, False, True), (True, True, False), (True, True, True))
SIZES = (1, 2, 4, 8)


def apply(image: np.ndarray, t: tuple[bool, bool, bool]) -> np.ndarray:
    """(H, W, ...) ``image`` transposed, then flipped as ``t`` says."""
    transpose, flip_y, flip_x = t
    out = image.swapaxes(0, 1) if transpose else image
    out = out[::-1] if flip_y else out
    return out[:, ::-1] if flip_x else out


def invert(image: np.ndarray, t: tuple[bool, bool, bool]) -> np.ndarray:
    """The inverse of ``apply(·, t)``: undo the flips, then the transpose."""
    transpose, flip_y, flip_x = t
    out = image[:, ::-1] if flip_x else image
    out = out[::-1] if flip_y else out
    return out.swapaxes(0, 1) if transpose else out


def ensemble(fn: Callable[[dict[str, np.ndarray]], np.ndarray], buffers: dict[str, np.ndarray],
             n: int) -> np.ndarray:
    """The mean of ``fn`` over the first ``n`` transforms of every (H, W, C) buffer, each output turned back."""
    if n not in SIZES:
        raise ValueError(f"a self-ensemble of {n} copies: expected one of {SIZES}")
    total = None
    for t in TRANSFORMS[:n]:
        out = invert(fn({k: np.ascontiguousarray(apply(v, t)) for k, v in buffers.items()}), t)
        total = out.astype(np.float64) if total is None else total + out
    return (total / n).astype(np.float32)
