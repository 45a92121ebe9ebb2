"""Time along a sequence: the input averaged over the neighbouring frames, the classic temporal filter, and the
instability metric.

What ``denoise --sequence`` and the sequence evaluation both run: first the frame's noisy input is averaged over a
window of frames (``InputWindow``), then the per-frame denoiser runs on it, then its outputs are filtered along
the sequence (``filtered``, the reprojection included); a model that reads the past is given its own previous
output instead (``step``).

**The input averaged** (``average_input``): the diffuse light (``diffuse_direct``, ``diffuse_indirect``) of
frame t averaged with that of up to ``window - 1`` frames before it and, for a sequence on disk whole, up to
``ahead`` frames after it, each reprojected into frame t (``motion.trace``: with cameras and depth straight,
with motion vectors along the chain of neighbours, backwards or forwards) and read at the pixel its spot falls in, over the frames
valid at each pixel and, with a ``gate``, agreeing with frame t within that many standard deviations of the difference; emission and
the reflections (the specular components) stay frame t's, since they do not follow the surface's motion. At
4 spp, 8 frames give most surfaces 32 samples of diffuse light. The filter below reads the frames after too where
the input does. The past pixels are read whole: an interpolated read correlates the noise of neighbouring pixels,
and a denoiser trained on white noise keeps correlated noise as detail (docs/sequences.md, "Read without
resampling", has both measurements).

The filter and the metric work on images already brought into the current frame
(``pipeline.motion.warp_previous``: the previous frame's image, read with the Catmull-Rom kernel on its
tonemapped values, with its validity mask), so they know nothing about cameras.

**The temporal filter** (``blend_history``) is what a renderer's TAA or a compositor's temporal
denoise node does with a per-frame denoiser's outputs: an exponential moving average

    h_t = w · y_t + (1 − w) · clamp(warp(h_{t−1}))      where the history is valid,
    h_t = y_t                                           elsewhere (first frame, off-screen, disoccluded),

with the history clamped, per channel, to the range of the current output's 3×3 neighbourhood
(Karis 2014, "High-quality temporal supersampling"). The clamp is what keeps a long history from
smearing: without it, a wrong history (a reprojection error, a moving highlight) never leaves. For a shot on
disk whole the filter reads both sides (``filtered`` with ``ahead``): the history is the mean of the causal
h_{t−1} and the same filter run backwards from the frames after, each warped and clamped:

    s_t = w · y_t + (1 − w) · ½ (clamp(warp(h_{t−1})) + clamp(warp(b_{t+1}))),   b_t = w · y_t + (1 − w) · clamp(warp(b_{t+1})).

**Temporal instability** (``instability``) measures flicker against the reference: over the pixels
valid in both frames, the mean absolute difference between the output's frame-to-frame change and
the reference's, each tonemapped (x/(1+x), the metrics' tonemap):

    I_t = mean_valid | (T(y_t) − T(warp(y_{t−1}))) − (T(r_t) − T(warp(r_{t−1}))) |

A denoiser whose error is the same in both frames (it follows the image) scores 0 however large
that error; noise that changes from frame to frame scores about its mean absolute size. Subtracting
the reference's change removes what legitimately changes (view-dependent shading, the reprojection's
own resampling), so a still, perfect sequence and a moving, perfect one both score 0 against a
noiseless reference. A reference with noise of its own (GT1 of an external scene) changes by that
noise too, which no method can follow: the true image then scores E|ΔGT1|, between half and all
of GT2's score (docs/sequences.md, "What the instability can measure").
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from . import motion
from .config import weight_problem
from .metrics import reinhard
from .schema import RADIANCE_COMPONENTS, beauty_from_components


def neighbourhood_range(image: np.ndarray, radius: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel and channel, the minimum and maximum of ``image`` over its (2·radius+1)² neighbourhood
    (edge pixels: the part of the window inside the image)."""
    h, w = image.shape[:2]
    pad = np.pad(image, ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    lo, hi = image.copy(), image.copy()
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            window = pad[dy:dy + h, dx:dx + w]
            np.minimum(lo, window, out=lo)
            np.maximum(hi, window, out=hi)
    return lo, hi


def blend_history(current: np.ndarray, history: np.ndarray | None, valid: np.ndarray | None, weight: float,
                  clamp: bool = True) -> np.ndarray:
    """One step of the temporal filter: ``current`` (H, W, C) blended with ``history`` (the filter's
    previous output warped into this frame) where ``valid``; ``weight`` is the new frame's share (1: no
    history). ``history`` None (the first frame) returns ``current`` unchanged."""
    return blend_sides(current, [] if history is None else [(history, valid)], weight, clamp)


def blend_sides(current: np.ndarray, sides: list[tuple[np.ndarray, np.ndarray | None]], weight: float,
                clamp: bool = True, box: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``blend_history`` with a history from each of ``sides`` ((history, valid): the frame before's, and for a
    shot on disk whole the frame after's): each clamped, then their mean where both are valid and the one valid
    history where only one is, blended with ``current`` at ``weight``; ``current`` where none is valid. ``box``:
    ``neighbourhood_range(current)`` when the caller has it already."""
    if (why := weight_problem(weight)) is not None:
        raise ValueError(f"blend weight: {why}")
    current = np.asarray(current, dtype=np.float32)
    if not sides:
        return current.copy()
    for history, valid in sides:
        if history.shape != current.shape or valid is None or valid.shape != current.shape[:2]:
            raise ValueError(f"history {getattr(history, 'shape', None)} / valid {getattr(valid, 'shape', None)} "
                             f"do not match the frame {current.shape}")
    lo, hi = (box if box is not None else neighbourhood_range(current)) if clamp else (None, None)
    total, count = np.zeros_like(current), np.zeros(current.shape[:2], np.float32)
    for history, valid in sides:           # whole-image operations with where=: no gather and scatter of pixels
        past = np.asarray(history, dtype=np.float32)
        past = np.clip(past, lo, hi) if clamp else past
        keep = valid.astype(bool)
        np.add(total, past, out=total, where=keep[..., None])
        count += keep
    blended = weight * current + (1.0 - weight) * (total / np.maximum(count, 1)[..., None])
    return np.where((count > 0)[..., None], blended, current)


# How many frames after frame t the backward filter starts from: frame t + 4 would weigh 0.2 % of frame t's output at
# weight 0.7, and 3 scores as the whole window to 0.001 dB (docs/sequences.md, "How far back the backward filter
# starts") at half its warps.
BACK_REACH = 3


def filtered(frames: Iterable[tuple[np.ndarray | None, motion.View | None]], weight: float, ahead: int = 0,
             reach: int | None = BACK_REACH) -> Iterator[tuple[np.ndarray | None, np.ndarray | None]]:
    """The temporal filter along a sequence: from (a per-frame output, None where it failed; its view) of each
    frame in order, yields (the frame's filtered output, its history's (H, W) validity or None without one), each
    once the ``ahead`` frames after it have come. ``ahead`` 0: the causal filter (module docstring); above 0, a shot
    on disk whole: frame t's history is the mean of the causal filter's output of frame t − 1 and the filter run
    backwards from frame t + min(``reach``, ``ahead``) (None: ``ahead``) to frame t + 1, each warped and clamped
    (``blend_sides``): the history's share is split between two sides whose lags point opposite ways
    (docs/sequences.md, "The filter on both sides"). The causal filter's own state stays its own: frame t's
    causal output is what frame t + 1 reads. Each pair of neighbours is reprojected once (``motion.reproject_view``),
    however many frames' backward filters pass through it."""
    reach = ahead if reach is None else min(reach, ahead)
    pending: deque = deque()            # (index, output, view) of the frames not yet yielded
    previous = None                     # (index, the causal filter's output, view) of the frame before
    traced: dict = {}                   # (i, j): where frame i's pixels are in its neighbour j, (xy, valid)

    def warp(image, i, view, j, other):
        """``image`` of frame j brought into frame i (j = i − 1, or i + 1 along the motion's to-next half)."""
        if (i, j) not in traced:
            traced[i, j] = motion.reproject_view(*((view, other) if j < i else map(motion.turned, (view, other))))
        return motion.warp_previous(image, view, other, traced[i, j])

    def backward(i, view):
        """The backward filter over the frames after frame i that it reaches, brought into frame i, or None."""
        chain = [(i, None, view)]
        for k, z, v in list(pending)[:reach]:
            if z is None or v is None or not motion.linked(motion.turned(chain[-1][2]), motion.turned(v)):
                break
            chain.append((k, z, v))
        if len(chain) == 1:
            return None
        back = chain[-1][1]
        for (k, z, v), (n, _, after) in zip(chain[-2:0:-1], chain[:1:-1]):   # the furthest first
            back = blend_history(z, *warp(back, k, v, n, after), weight)
        return warp(back, i, view, chain[1][0], chain[1][2])

    def finish():
        nonlocal previous
        i, y, view = pending.popleft()
        for key in [key for key in traced if max(key) <= i]:
            del traced[key]
        if y is None:
            previous = None
            return None, None
        linked = previous is not None and view is not None and previous[2] is not None \
            and motion.linked(view, previous[2])
        sides = [warp(previous[1], i, view, previous[0], previous[2])] if linked else []
        box = neighbourhood_range(np.asarray(y, np.float32))        # the clamp's range, for both blends
        causal = blend_sides(y, sides, weight, box=box)
        back = backward(i, view) if reach and view is not None else None
        previous, sides = (i, causal, view), sides + ([] if back is None else [back])
        return blend_sides(y, sides, weight, box=box) if back is not None else causal, \
            np.logical_or.reduce([v for _, v in sides]) if sides else None

    for i, (y, view) in enumerate(frames):
        pending.append((i, y, view))
        if len(pending) > ahead:
            yield finish()
    while pending:
        yield finish()


# What ``average_input`` averages, per kind, in groups that its gate tests together: every radiance buffer as
# one, only the view-independent diffuse light (the rest of the frame stays frame t's: reflections do not follow
# the surface's motion), or every component with the diffuse light and each reflection gated apart.
# ``irradiance`` is the diffuse light demodulated by the albedo: averaged as the diffuse light divided by each
# frame's own albedo, then multiplied by frame t's, so a texture stays frame t's (SVGF, Schied et al. 2017).
GATE_GROUPS = {"colour": (("color", *RADIANCE_COMPONENTS),),
               "diffuse": (("diffuse_direct", "diffuse_indirect"),),
               "irradiance": (("diffuse_direct", "diffuse_indirect"),),
               "components": (("diffuse_direct", "diffuse_indirect"), ("specular_direct",), ("specular_indirect",))}
AVERAGED = {kind: tuple(n for g in groups for n in g) for kind, groups in GATE_GROUPS.items()}
DEMODULATED = {"irradiance"}
ALBEDO_FLOOR = 1e-3     # below it a channel's albedo is black: its light is averaged as it is, not divided


def average_input(buffers: dict[str, np.ndarray], past: list[dict[str, np.ndarray]],
                  traced: list[tuple[np.ndarray, np.ndarray]], kind: str = "diffuse", kernel: str = "nearest",
                  gate: float | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(frame t's ``buffers`` with its noisy radiance averaged over frame t and the ``past`` frames, the (H, W)
    number of frames averaged at each pixel, of the first group).

    ``traced``: where frame t's pixels were in each past frame (``motion.trace``, one per frame of ``past``). A
    past frame counts at a pixel where it is valid there, read at the pixel the spot falls in (``motion.warp``
    with ``kernel="nearest"``: an interpolated read correlates the noise, and the denoiser keeps it,
    docs/sequences.md; ``kernel`` is there to measure that). ``kind`` (``GATE_GROUPS``): ``colour`` averages
    every radiance buffer present (the beauty and its components); ``diffuse`` the two diffuse components,
    ``components`` the diffuse and the specular ones, ``irradiance`` the diffuse ones divided by each frame's albedo
    (per channel, where above ``ALBEDO_FLOOR``; a past pixel counts only where the same channels are), then
    multiplied by frame t's, the beauty then the sum of the components (the averaged
    ones and frame t's others) with frame t's emission (a frame without the components is left alone: its beauty
    averaged would carry reflections along with the surface, which loses up to 8 dB on glossy scenes,
    docs/sequences.md). A buffer's variance (the variance of the pixel estimate) becomes the mean of the frames'
    divided by their number, each frame's noise independent of the others'; the beauty's, for ``diffuse`` and
    ``components``, frame t's with the averaged components' share so replaced. Every other buffer is frame t's.
    ``gate`` (where the variances are there): a past frame counts at a pixel only where, in every channel, the
    light of a group (summed over its buffers) differs from frame t's by at most ``gate`` standard deviations of
    the difference, sqrt(var_t + var_past): what differs by more than noise is another surface, another part of a
    texture or light that changed with the view. Each group is gated (and counted) apart."""
    if len(past) != len(traced):
        raise ValueError(f"{len(past)} past frames but {len(traced)} traced")
    if kind not in GATE_GROUPS:
        raise ValueError(f"kind must be one of {', '.join(GATE_GROUPS)}, got {kind!r}")
    out, counts = dict(buffers), []
    if kind != "colour" and not all(n in buffers for n in RADIANCE_COMPONENTS):
        return out, np.ones(buffers["color"].shape[:2])  # no components to tell the diffuse light from reflections
    albedo = kind in DEMODULATED and "albedo" in buffers
    for names in GATE_GROUPS[kind]:
        averaged, count = _average_group(buffers, past, traced, [n for n in names if n in buffers], kernel, gate,
                                         albedo)
        out.update(averaged)
        counts.append(count)
    if kind != "colour":
        out["color"] = beauty_from_components(out)
        if all(f"{n}.variance" in buffers for n in ("color", *AVERAGED[kind])):
            share = sum(out[f"{n}.variance"].astype(np.float64) - buffers[f"{n}.variance"] for n in AVERAGED[kind])
            out["color.variance"] = np.maximum(buffers["color.variance"] + share, 0).astype(np.float32)
    return out, counts[0]


def _average_group(buffers, past, traced, names, kernel, gate, albedo=False) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(the buffers ``names`` and their variances averaged as ``average_input`` says, their count (H, W)); with
    ``albedo``, averaged as the light divided by each frame's albedo, then multiplied by frame t's."""
    count = np.ones(buffers["color"].shape[:2])
    keys = [k for n in names for k in (n, f"{n}.variance") if k in buffers]
    albedo = albedo and all("albedo" in frame for frame in past)
    mine_lit = buffers["albedo"].astype(np.float64) > ALBEDO_FLOOR if albedo else None
    total = _demodulated({k: buffers[k].astype(np.float64) for k in keys}, buffers, mine_lit)
    gated = gate is not None and all(f"{n}.variance" in buffers for n in names)
    if gated:
        mine = sum(total[n] for n in names)
        my_var = sum(total[f"{n}.variance"] for n in names)
    for frame, (xy, valid) in zip(past, traced):
        if not all(k in frame for k in keys):
            break                       # a frame without those layers ends the window
        read = _warp_together(frame, [k for k in (*keys, "albedo") if k in keys or albedo], xy, valid, kernel)
        if albedo:
            lit = read["albedo"].astype(np.float64) > ALBEDO_FLOOR      # as frame t's: compared in float64
            valid = valid & motion.every_channel(lit == mine_lit)   # a channel black in one frame only: another surface
            read = _demodulated(read, read, lit)
        if gated:
            theirs = _sum64([read[n] for n in names])
            spread = np.sqrt(my_var + _sum64([read[f"{n}.variance"] for n in names]))
            valid = valid & motion.every_channel(np.abs(theirs - mine) <= gate * spread)
        for k in keys:                  # a float32 read is widened by the addition itself
            np.add(total[k], read[k], out=total[k], where=valid[..., None])
        count += valid
    mean = {k: total[k] / count[..., None] ** (2 if k.endswith(".variance") else 1) for k in keys}
    if albedo:                          # modulated again by frame t's albedo: the texture is this frame's
        a = np.where(mine_lit, buffers["albedo"].astype(np.float64), 1.0)
        mean = {k: v * (a * a if k.endswith(".variance") else a) for k, v in mean.items()}
    return {k: v.astype(np.float32) for k, v in mean.items()}, count


def _warp_together(frame: dict[str, np.ndarray], names: list[str], xy: np.ndarray, valid: np.ndarray,
                   kernel: str) -> dict[str, np.ndarray]:
    """``motion.warp`` of each of ``frame``'s ``names``, read in one call on their channels side by side: the same
    values (each channel is read on its own) for a quarter of the indexing. Each comes back contiguous (the
    arithmetic on it runs twice as fast as on a slice of the block), in the frame's dtype: the float64 sums widen it
    as they add, without a float64 copy of every layer."""
    images = [frame[n] if frame[n].ndim == 3 else frame[n][..., None] for n in names]
    block = motion.warp(np.concatenate(images, axis=-1), xy, valid, kernel=kernel)
    ends = np.cumsum([im.shape[2] for im in images])
    return {n: np.ascontiguousarray(block[..., end - im.shape[2]:end]).reshape(frame[n].shape)
            for n, im, end in zip(names, images, ends)}


def _sum64(images: list[np.ndarray]) -> np.ndarray:
    """The sum of ``images`` in float64, each widened as it is added (a new array)."""
    out = images[0].astype(np.float64)
    for image in images[1:]:
        out += image
    return out


def _demodulated(values: dict[str, np.ndarray], frame: dict[str, np.ndarray], lit: np.ndarray | None) -> dict:
    """``values`` (light and variances) divided by ``frame``'s albedo (squared for a variance) in the channels
    where ``lit`` (albedo above ``ALBEDO_FLOOR``); as they are without ``lit``."""
    if lit is None:
        return values
    a = np.where(lit, frame["albedo"].astype(np.float64), 1.0)
    return {k: v / (a * a if k.endswith(".variance") else a) for k, v in values.items() if k != "albedo"}


def averaging_kind(buffers: dict[str, np.ndarray]) -> str:
    """What ``average_input`` averages of a sequence whose frames are like ``buffers``: the diffuse light where the
    frame has the variances its gate reads; the diffuse light divided by the albedo where it has not (a Cycles
    render): nothing then refuses a past pixel read up to half a pixel off, and on a fine texture that blurs the
    texture, while the light under it is smooth (docs/sequences.md, "Without variances")."""
    gated = all(f"{n}.variance" in buffers for n in GATE_GROUPS["diffuse"][0])
    return "diffuse" if gated or "albedo" not in buffers else "irradiance"


def describe_averaging(window: int, ahead: int = 0, gate: float | None = None) -> str | None:
    """How the temporal methods average their input, in words (the sequence page, row labels, a history pack's
    record): 'diffuse light over 8 frames and 7 after, gate 2'; None when nothing is averaged."""
    if window <= 1 and not ahead:
        return None
    return (f"diffuse light over {window} frames" + (f" and {ahead} after" if ahead else "")
            + (f", gate {gate:g}" if gate else ""))


class InputWindow:
    """The noisy radiance and the views of the last ``frames - 1`` frames, which ``take`` averages each new
    frame's input over (``average_input``), with up to ``ahead`` frames after it that the caller gives (a sequence
    on disk whole); ``frames`` 1 and ``ahead`` 0 average nothing."""

    def __init__(self, frames: int, kind: str = "diffuse", gate: float | None = None, ahead: int = 0):
        if frames < 1:
            raise ValueError(f"a window of {frames} frames: must be >= 1")
        if ahead < 0:
            raise ValueError(f"{ahead} frames ahead: must be >= 0")
        if kind not in GATE_GROUPS:
            raise ValueError(f"kind must be one of {', '.join(GATE_GROUPS)}, got {kind!r}")
        self.frames, self.kind, self.gate, self.ahead = frames, kind, gate, ahead
        self.past: list[tuple[dict[str, np.ndarray], motion.View | None]] = []    # the latest first
        self.counts: list[float] = []              # per frame averaged with another, the mean frames per pixel

    def keep(self, buffers: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """What of a frame's buffers the window averages (at 1920x1080 the diffuse light and its variance are
        100 MB a frame): all a caller needs to hold of the frames ahead."""
        kept = {k: buffers[k] for n in AVERAGED[self.kind] for k in (n, f"{n}.variance") if k in buffers}
        if self.kind in DEMODULATED and "albedo" in buffers:
            kept["albedo"] = buffers["albedo"]
        return kept

    def take(self, buffers: dict[str, np.ndarray], view: motion.View | None,
             upcoming: list[tuple[dict[str, np.ndarray], motion.View | None]] = ()) -> dict[str, np.ndarray]:
        """This frame's buffers averaged over the window and the first ``ahead`` frames of ``upcoming`` (the
        frames after it, in order; ``keep`` of their buffers is enough), then the frame joins the window."""
        if self.frames == 1 and self.ahead == 0:
            return buffers
        traced, others = [], []
        if view is not None:
            linked_views = []
            for _, v in self.past:
                if v is None:
                    break
                linked_views.append(v)
            traced = motion.trace(view, linked_views)
            others = [b for b, _ in self.past[:len(traced)]]
            later = []
            for b, v in list(upcoming)[:self.ahead]:
                if v is None:
                    break
                later.append((b, v))
            found = motion.trace(view, [v for _, v in later], ahead=True)
            traced += found
            others += [b for b, _ in later[:len(found)]]
        out, count = average_input(buffers, others, traced, self.kind, gate=self.gate)
        if others:
            self.counts.append(float(count.mean()))
        else:
            out = buffers                  # the frame's own input, as the per-frame method saw it
        self.past = [(self.keep(buffers), view), *self.past][: self.frames - 1]
        return out


def step(denoise: Callable[[dict, tuple | None], np.ndarray | None], buffers: dict[str, np.ndarray],
         view: motion.View | None, previous: tuple[np.ndarray | None, motion.View | None] | None
         ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """One frame of a model that reads the past (``diffusion.history``): (its output, None where ``denoise``
    failed; the history's (H, W) validity, None without a history). The per-frame methods are filtered instead
    (``filtered``).

    ``previous``: (the model's output of the previous frame, that frame's view); the history is that output
    warped into ``view`` (``motion.warp_previous``), none on a first frame, after a frame that failed or
    where the two frames share no motion (``motion.linked``: motion vectors, or cameras with depth).
    ``denoise(buffers, history)`` is the model given the history as condition channels.
    ``buffers``: the frame's input as the model denoises it, averaged over the neighbouring frames where the caller
    keeps an ``InputWindow`` (one window serves every temporal method of a sequence)."""
    history = None
    if (previous is not None and previous[0] is not None and view is not None and previous[1] is not None
            and motion.linked(view, previous[1])):
        history = motion.warp_previous(previous[0], view, previous[1])
    y = denoise(buffers, history)
    return y, None if y is None or history is None else history[1]


def instability(output: np.ndarray, output_prev_warped: np.ndarray, reference: np.ndarray,
                reference_prev_warped: np.ndarray, valid: np.ndarray) -> float:
    """Temporal instability of ``output`` at one frame (see the module docstring); NaN when no pixel is
    valid. All images (H, W, C) linear HDR, the previous frames already warped into this one."""
    keep = np.asarray(valid, dtype=bool)
    if not keep.any():
        return float("nan")
    change = reinhard(np.asarray(output, np.float64)) - reinhard(np.asarray(output_prev_warped, np.float64))
    truth = reinhard(np.asarray(reference, np.float64)) - reinhard(np.asarray(reference_prev_warped, np.float64))
    return float(np.abs(change - truth)[keep].mean())
