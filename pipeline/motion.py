"""Cameras of a sequence, and how pixels move between its frames: projection, reprojection, warping.

Pure numpy; what temporal denoising needs to bring frame t-1 onto frame t.

Conventions
-----------
* **Camera** (``Camera``): Mitsuba's perspective pinhole. ``camera_to_world`` is the sensor's
  ``to_world`` (columns: left, up, forward, origin; orthonormal, a mirrored camera's first column
  may point right); ``fov_x`` the field of view in degrees across the film's ``width`` (Mitsuba's
  ``x_fov``); square pixels, principal point at the image centre; ``near``/``far`` the clip distances.
  In the camera's local frame a point (x, y, z) with z > 0 is in front and lands at

      px = W/2 (1 - x / (z tan(fov_x/2))),   py = H/2 - (W/2) y / (z tan(fov_x/2))

  (local +x is the image's left, +y its top: Mitsuba's ``camera_to_sample`` transform).
* **Pixel coordinates**: continuous, x to the right, y down, (0, 0) the upper left corner of the
  image. Pixel (i, j) (column i, row j) covers [i, i+1) x [j, j+1) and its centre is (i + 0.5, j + 0.5):
  the store's film is box-filtered without sample border, so every sample lands in the pixel it falls in.
* **Depth** (the store's ``depth`` buffer, ``render.integrator``): camera-space z, ``dot(p - o, forward)``,
  not the distance along the ray; 0 where the camera ray escapes (background). It is the mean over
  the pixel's samples, so it is z at the pixel centre up to z's variation inside the pixel (exact on a
  surface facing the camera; a silhouette pixel averages its surfaces, and 0 for the background).

Reprojection (``reproject``)
----------------------------
Each pixel centre of frame t with depth > 0 is unprojected to its world point and projected into
frame t-1. It is **invalid** when

* its depth is 0 (background: no point to follow);
* it lands off frame t-1 (outside [0, W] x [0, H]) or not in front of that camera (z <= near);
* (``depth_prev`` given) disoccluded: frame t-1 sees another surface there. The test reads the
  four pixel centres around the landing spot (the bilinear footprint the warp reads, clamped at the
  image border; taps of weight below ``TAP_EPS`` are left out). A footprint with a background tap is
  invalid; otherwise the bilinear interpolation of 1/depth_prev is compared with the point's own
  z in frame t-1: invalid when |z / z_seen - 1| > ``depth_tolerance``. 1/z is affine in screen
  coordinates on a plane, so on planes the interpolation is exact (up to the pixel-mean of depth)
  and the test does not depend on the surface's slant; a footprint straddling two surfaces at depth
  ratio r > 1 reads a mixed 1/z and is caught once the other surface's taps weigh more than
  tolerance / (r - 1) for a point on the far surface, tolerance * r / (r - 1) for one on the near surface
  (the relative error of 1/z is that weight times r - 1, or times (r - 1) / r);
* (``normal_t`` and ``normal_prev`` given) the world-space shading normals disagree: the
  bilinearly read normal of t-1, normalised, has a dot product below ``normal_threshold`` with
  frame t's (world-space normals of a point do not change when the camera moves).

Warping (``warp``)
------------------
Bilinear interpolation of the image of t-1 at ``xy_prev`` over the same four taps (clamped at the
border, weights below ``TAP_EPS`` dropped and the rest renormalised, so a landing spot on a pixel
centre returns that pixel exactly); invalid pixels are 0. Where ``valid`` comes from ``reproject``
with ``depth_prev``, a valid pixel's footprint holds no background tap, and one straddling two
surfaces at depth ratio r passes only while the other surface's taps weigh at most the bounds
above: the warp blends across a silhouette by up to tolerance * r / (r - 1) (0.1 at the default
tolerance and r = 2), and across surfaces of nearly equal depth freely.

``warp_previous``, what a temporal method's history is read with, uses the **Catmull-Rom** kernel
instead (``warp(..., kernel="catmull_rom")``: 4x4 taps, clamped at the border, negative results set to 0),
as TAA implementations read their history: bilinear reads blur the history a little more at every frame it
is carried, and the sharper read gains 0.06-0.07 dB for the temporal filter (docs/sequences.md, "The
history's resampling"). It reads a pixel centre exactly too; its wider footprint reaches one pixel further
across a silhouette than the validity test looks. It reads the **tonemapped** image, x / (1 + x)
(``metrics.reinhard``), and brings the result back to radiance (``metrics.inverse_reinhard``), capped at the
image's brightest pixel: interpolated on radiance, a light of radiance 100 a pixel away puts tens of units into
its dark neighbour at a sub-pixel offset (more with the kernel's overshoot), which the filter's clamp lets
through since the light is in the neighbourhood; on x / (1 + x) its share is bounded by the read's weight
(docs/sequences.md, "The history's read around small bright lights"). The metrics' warp
(``evaluate.sequence``) stays bilinear and on radiance.

A past frame's noisy *input* is read with ``kernel="nearest"``, the pixel the landing spot falls in, whole:
any interpolation mixes neighbouring pixels' noise, and a denoiser trained on white noise keeps the
correlated noise of an interpolated input as detail (docs/sequences.md, "Read without resampling"). The spot is
then off by at most half a pixel.

Further back (``trace``)
------------------------
Averaging a window of frames needs where frame t's pixels were in frames t-2, t-3, ... too. With cameras and
depth each past frame is reached directly (``reproject`` between t and t-k: one landing spot, no error carried
from frame to frame). Motion vectors only link neighbours, so the way back is chained: the spot in t-1, then
frame t-1's own ``flow`` into t-2 read bilinearly there (its validity at the pixel the spot falls in), and so on.
The way forward (``trace(..., ahead=True)``, the frames after t of a sequence on disk whole) is the same with
the two halves of every frame's motion exchanged: ``to_next`` leads into t+1 and t+1's ``to_prev`` tests it.

Motion vectors (``flow``, ``from_blender_vectors``)
--------------------------------------------------
A renderer that writes its own motion (Blender's ``Vector`` pass) needs neither camera nor depth, and its
vectors follow moving objects too. Here a frame's motion is (H, W, 4): ``to_prev`` (where the pixel's point
was in frame t-1, minus where it is now) and ``to_next`` (where it will be in frame t+1, minus now), in the
pixel coordinates above. Pixel p of frame t lands at q = p + to_prev(p) in frame t-1. It is **invalid** when q
is off frame t-1, or when frame t-1's own ``to_next`` read bilinearly at q (the warp's footprint) does not
bring q back to within ``tolerance`` pixels of p: q shows another surface in frame t-1 (a disocclusion, or a
footprint straddling a silhouette, whose vectors mix two motions), the forward-backward test of optical
flow. Where both frames have depth (Blender's ``Depth`` pass) it is also invalid when frame t-1's depth at q
differs from frame t's by more than ``FLOW_DEPTH_TOLERANCE`` of it: the forward-backward test cannot tell an
occluder from what it hides where their motions differ by less than ``tolerance`` (small camera moves), the depth
can. There is no normal test: Blender's ``Denoising Normal`` is in camera space, so it turns with the camera.

OpenEXR headers (``exr_matrices``, ``camera_from_exr``)
------------------------------------------------------
Store images carry the standard attributes ``worldToCamera`` and ``worldToNDC`` (``m44f``), as
OpenEXR defines them: Imath's **row-vector** convention, p' = p M with p = (x, y, z, 1), so the
stored matrix is the transpose of the column-vector matrix used here (M[3] holds the translation).
Camera space is RenderMan's: left-handed, x right, y up, z forward (Mitsuba's local x negated).
NDC: (0, 0) the upper left and (1, 1) the lower right corner of the image, so pixel coordinates are
(W x_ndc, H y_ndc) after the homogeneous divide; NDC z is Mitsuba's perspective depth (0 at near,
1 at far).
"""
from __future__ import annotations

import functools
import math
import operator
from dataclasses import dataclass

import numpy as np

from .errors import StoreError
from .metrics import inverse_reinhard, reinhard

# Bilinear taps lighter than this are left out of the footprint (and the rest renormalised): a landing
# spot within 1e-3 pixel of a centre reads that pixel alone, so round-off never brings in a neighbour.
TAP_EPS = 1e-3
# Default tolerances of reproject: a relative depth mismatch of 5 % is far above the pixel-mean and
# the compact encoding's depth rounding (2^-11), and far below the depth steps between objects.
DEPTH_TOLERANCE = 0.05
NORMAL_THRESHOLD = 0.9          # cos 25.8 degrees: half-float normals, curved surfaces' footprints
# Default forward-backward tolerance of flow, in pixels: far above half-float vectors' rounding (2^-11 relative)
# and bilinear interpolation's error on a smooth flow, below the mismatch of two surfaces' motions.
FLOW_TOLERANCE = 0.5
# Default depth test of flow where both frames have depth: a point's depth changes between two frames of a camera
# move by a few per cent (a dolly of a fifth of the distance over 8 frames: 2.5 %), the step from an occluder to
# what it hides by far more. Without cameras the change cannot be predicted, so the test is this loose.
FLOW_DEPTH_TOLERANCE = 0.1
# Clip distances of the store's cameras (render.buffers.make_sensor) and of a frame record that lacks them.
NEAR_CLIP = 1e-3
FAR_CLIP = 1e4
# OpenEXR camera space (x right) from Mitsuba's local camera space (x left).
_FLIP_X = np.diag([-1.0, 1.0, 1.0, 1.0])


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera of one frame (module docstring: conventions)."""
    camera_to_world: np.ndarray     # 4x4 float64, Mitsuba's to_world (columns left, up, forward, origin)
    fov_x: float                    # degrees across the width
    width: int
    height: int
    near: float = NEAR_CLIP
    far: float = FAR_CLIP

    def __post_init__(self):
        m = np.asarray(self.camera_to_world, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"camera_to_world must be a finite 4x4 matrix, got shape {m.shape}")
        if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
            raise ValueError(f"camera_to_world's last row must be [0, 0, 0, 1], got {m[3].tolist()}")
        if not np.allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-4):
            raise ValueError("camera_to_world's first three columns must be orthonormal (a rigid camera)")
        if not (math.isfinite(self.fov_x) and 0 < self.fov_x < 180):
            raise ValueError(f"fov_x must be in (0, 180) degrees, got {self.fov_x!r}")
        if not (int(self.width) == self.width >= 1 and int(self.height) == self.height >= 1):
            raise ValueError(f"width and height must be positive integers, got {self.width!r}x{self.height!r}")
        if not (0 <= self.near < self.far):
            raise ValueError(f"need 0 <= near < far, got near={self.near!r}, far={self.far!r}")
        object.__setattr__(self, "camera_to_world", m)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def tan_half(self) -> float:
        """tan(fov_x / 2): the half-width of the image plane at unit depth."""
        return math.tan(math.radians(self.fov_x) / 2)

    def world_to_camera(self) -> np.ndarray:
        """4x4 column-vector matrix from world to Mitsuba's local camera frame (x left, y up, z forward)."""
        return np.linalg.inv(self.camera_to_world)


# ---- projection ------------------------------------------------------------------------------

def pixel_centres(width: int, height: int) -> np.ndarray:
    """[H, W, 2] float64 pixel coordinates (x, y) of every pixel centre: (i + 0.5, j + 0.5)."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64) + 0.5
    return np.stack([x, y], axis=-1)


def project(points_world: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """World points [..., 3] -> (pixel coordinates [..., 2], camera-space z [...]), float64.

    Points with z <= 0 (behind the camera) get non-finite or meaningless pixel coordinates: test z."""
    p = np.asarray(points_world, dtype=np.float64)
    m = cam.world_to_camera()
    local = p @ m[:3, :3].T + m[:3, 3]
    z = local[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        sx = local[..., 0] / (z * cam.tan_half)
        sy = local[..., 1] / (z * cam.tan_half)
    xy = np.stack([cam.width / 2 * (1 - sx), cam.height / 2 - cam.width / 2 * sy], axis=-1)
    return xy, z


def unproject(depth: np.ndarray, cam: Camera, xy: np.ndarray | None = None) -> np.ndarray:
    """World points [H, W, 3] float64 seen at each pixel centre (or at ``xy`` [..., 2]) at camera-space
    z = ``depth`` ([H, W] or [H, W, 1], the store's depth buffer); NaN where depth <= 0 (background)."""
    z = np.asarray(depth, dtype=np.float64)
    if z.ndim == 3 and z.shape[2] == 1:
        z = z[..., 0]
    if xy is None:
        if z.shape != (cam.height, cam.width):
            raise ValueError(f"depth is {z.shape}, the camera's image {cam.height}x{cam.width}")
        xy = pixel_centres(cam.width, cam.height)
    t = cam.tan_half
    x_over_z = (1 - 2 * xy[..., 0] / cam.width) * t
    y_over_z = (cam.height / 2 - xy[..., 1]) * 2 / cam.width * t
    local = np.stack([x_over_z * z, y_over_z * z, z], axis=-1)
    m = cam.camera_to_world
    world = local @ m[:3, :3].T + m[:3, 3]
    world[~(z > 0)] = np.nan
    return world


# ---- bilinear footprints ---------------------------------------------------------------------

def _footprint(xy: np.ndarray, width: int, height: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The four bilinear taps (pixel: row * width + column, weight) around each of ``xy`` [N, 2] (finite), clamped
    at the border; weights below TAP_EPS set to 0 and the rest renormalised to sum 1."""
    u = np.clip(xy[:, 0] - 0.5, 0, width - 1)
    v = np.clip(xy[:, 1] - 0.5, 0, height - 1)
    i0 = np.minimum(np.floor(u).astype(np.int64), max(width - 2, 0))
    j0 = np.minimum(np.floor(v).astype(np.int64), max(height - 2, 0))
    fx, fy = u - i0, v - j0
    i1, j1 = np.minimum(i0 + 1, width - 1), np.minimum(j0 + 1, height - 1)
    r0, r1 = j0 * width, j1 * width
    taps = [(r0 + i0, (1 - fx) * (1 - fy)), (r0 + i1, fx * (1 - fy)), (r1 + i0, (1 - fx) * fy), (r1 + i1, fx * fy)]
    weights = np.stack([w for _, w in taps])
    weights[weights < TAP_EPS] = 0.0
    weights /= weights.sum(axis=0, keepdims=True)
    return [(flat, w) for (flat, _), w in zip(taps, weights)]


def every_channel(mask: np.ndarray) -> np.ndarray:
    """``mask`` [..., C] true in all C channels: [...]; ``mask.all(axis=-1)``, several times faster for a few
    channels (numpy reduces a short last axis slowly)."""
    return functools.reduce(operator.and_, (mask[..., c] for c in range(mask.shape[-1])))


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Sum over the last axis of ``a * b`` [N, C], the channels added in order as ``(a * b).sum(axis=-1)`` does."""
    return functools.reduce(operator.add, (a[:, c] * b[:, c] for c in range(a.shape[-1])))


def _flat(image: np.ndarray) -> np.ndarray:
    """``image`` [H, W, C] as [H * W, C], read with ``.take(row * width + column, axis=0)``: one index into the
    flattened image is several times faster than numpy's two-array indexing, same values. Made once per image
    and reused for every tap (a strided image is copied by the reshape)."""
    return image.reshape(-1, image.shape[2])


def _read(image: np.ndarray, taps) -> np.ndarray:
    """Bilinear read of ``image`` [H, W, C] over ``taps``: [N, C] float64 (the product with the float64 weights
    widens a float32 image's pixels)."""
    pixels = _flat(image)
    return sum(w[:, None] * pixels.take(flat, axis=0) for flat, w in taps)


def _channels(a: np.ndarray | None) -> np.ndarray | None:
    if a is None:
        return None
    a = np.asarray(a)
    return a[..., None] if a.ndim == 2 else a


# ---- reprojection and warping ----------------------------------------------------------------

def reproject(depth_t: np.ndarray, cam_t: Camera, cam_prev: Camera, depth_prev: np.ndarray | None = None,
              normal_t: np.ndarray | None = None, normal_prev: np.ndarray | None = None,
              depth_tolerance: float = DEPTH_TOLERANCE, normal_threshold: float = NORMAL_THRESHOLD,
              world_t: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of frame t was in frame t-1: (xy_prev [H, W, 2] float32 pixel coordinates of t-1,
    valid [H, W] bool). xy_prev is NaN on the background of t; its value elsewhere is where the point
    projects even when invalid. The tests that make a pixel invalid: module docstring. ``world_t``:
    ``unproject(depth_t, cam_t)`` where the caller has it (frame t followed into several frames)."""
    z_t = _channels(depth_t)[..., 0].astype(np.float64)
    world = unproject(z_t, cam_t) if world_t is None else world_t
    xy, z = project(world, cam_prev)
    valid = (z_t > 0) & (z > cam_prev.near) & every_channel(np.isfinite(xy))
    valid &= (xy[..., 0] >= 0) & (xy[..., 0] <= cam_prev.width) & (xy[..., 1] >= 0) & (xy[..., 1] <= cam_prev.height)
    idx = np.nonzero(valid)
    if idx[0].size and (depth_prev is not None or normal_prev is not None):
        taps = _footprint(xy[idx], cam_prev.width, cam_prev.height)
        keep = np.ones(idx[0].size, dtype=bool)
        if depth_prev is not None:
            d_prev = _channels(depth_prev).astype(np.float64)
            if d_prev.shape[:2] != (cam_prev.height, cam_prev.width):
                raise ValueError(f"depth_prev is {d_prev.shape[:2]}, the camera's image {cam_prev.height}x{cam_prev.width}")
            keep &= _depth_agrees(z[idx], d_prev, taps, depth_tolerance)
        if normal_t is not None and normal_prev is not None:
            keep &= _normals_agree(normal_t, normal_prev, idx, taps, normal_threshold)
        valid[idx] = keep
    xy = xy.astype(np.float32)
    xy[~(z_t > 0)] = np.nan
    return xy, valid


def _normals_agree(normal_t: np.ndarray, normal_prev: np.ndarray, idx, taps, threshold: float) -> np.ndarray:
    """For the pixels ``idx`` of frame t: whether frame t-1's normal, read over ``taps`` and normalised, has a dot
    product of at least ``threshold`` with frame t's."""
    n_prev = _read(np.asarray(normal_prev), taps)
    n_t = np.asarray(normal_t)[idx].astype(np.float64)
    norms = np.sqrt(_dot(n_prev, n_prev)) * np.sqrt(_dot(n_t, n_t))
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = np.where(norms > 0, _dot(n_prev, n_t) / norms, -1.0)
    return cos >= threshold


def flow(motion_t: np.ndarray, motion_prev: np.ndarray, tolerance: float = FLOW_TOLERANCE,
         depth_t: np.ndarray | None = None, depth_prev: np.ndarray | None = None,
         depth_tolerance: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``reproject``'s answer from motion vectors: (xy_prev [H, W, 2] float32, valid [H, W] bool) for frame t
    of motion ``motion_t`` (H, W, 4) after frame t-1 of motion ``motion_prev``; xy_prev is NaN where the vector
    is not finite. The tests that make a pixel invalid: module docstring; with both frames' depth (H, W) also
    where frame t-1's depth read at the landing spot (as ``reproject`` reads it: the inverse, bilinearly) differs
    from frame t's by more than ``depth_tolerance`` (None: ``FLOW_DEPTH_TOLERANCE``) of it, or either is background
    (not above 0)."""
    m_t, m_prev = np.asarray(motion_t, np.float64), np.asarray(motion_prev, np.float64)
    if m_t.ndim != 3 or m_t.shape[2] != 4 or m_prev.ndim != 3 or m_prev.shape[2] != 4:
        raise ValueError(f"motion must be (H, W, 4), got {m_t.shape} and {m_prev.shape}")
    h, w = m_prev.shape[:2]
    centres = pixel_centres(m_t.shape[1], m_t.shape[0])
    xy = centres + m_t[..., :2]
    valid = every_channel(np.isfinite(xy))
    xy[~valid] = np.nan
    with np.errstate(invalid="ignore"):
        valid &= (xy[..., 0] >= 0) & (xy[..., 0] <= w) & (xy[..., 1] >= 0) & (xy[..., 1] <= h)
    idx = np.nonzero(valid)
    if idx[0].size:
        taps = _footprint(xy[idx], w, h)
        with np.errstate(invalid="ignore", over="ignore"):      # a non-finite vector fails the test
            back = xy[idx] + _read(m_prev[..., 2:], taps)
            miss = back - centres[idx]
            keep = np.sqrt(_dot(miss, miss)) <= tolerance
        if depth_t is not None and depth_prev is not None:
            keep &= _depth_agrees(_channels(depth_t)[..., 0][idx], _channels(depth_prev), taps,
                                  FLOW_DEPTH_TOLERANCE if depth_tolerance is None else depth_tolerance)
        valid[idx] = keep
    return xy.astype(np.float32), valid


def _depth_agrees(z_t: np.ndarray, depth_prev: np.ndarray, taps, tolerance: float) -> np.ndarray:
    """Per landing spot (``taps``), whether frame t-1's depth there, its inverse read bilinearly over a footprint
    with no background tap (module docstring), is within ``tolerance`` of ``z_t`` (above 0): the depth the point
    should have there (``reproject``: predicted by the two cameras; ``flow``: frame t's own)."""
    d_prev = np.asarray(depth_prev, np.float64)
    background, depths = np.zeros(len(z_t), dtype=bool), d_prev.reshape(-1)
    for flat, w in taps:
        background |= (w > 0) & ~(depths.take(flat) > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        seen = _read(np.where(d_prev > 0, 1.0 / d_prev, 0.0), taps)[:, 0]
        return ~background & (z_t > 0) & (np.abs(np.asarray(z_t, np.float64) * seen - 1) <= tolerance)


def from_blender_vectors(vector: np.ndarray) -> np.ndarray:
    """This module's motion (H, W, 4) float32 from Blender's ``Vector`` pass (X, Y, Z, W; rows top-down as its
    EXR stores them). Cycles writes, in raster coordinates with y **up** (``primitive_motion_vector``):
    (X, Y) = where the point was in the previous frame minus where it is, (Z, W) = where it is minus where it
    will be. So ``to_prev`` = (X, -Y) and ``to_next`` = (-Z, W) in pixel coordinates with y down."""
    v = np.asarray(vector, dtype=np.float32)
    if v.ndim != 3 or v.shape[2] != 4:
        raise ValueError(f"a Vector pass is (H, W, 4), got {v.shape}")
    return np.stack([v[..., 0], -v[..., 1], -v[..., 2], v[..., 3]], axis=-1)


KERNELS = ("bilinear", "catmull_rom", "nearest")


def warp(image_prev: np.ndarray, xy_prev: np.ndarray, valid: np.ndarray, kernel: str = "bilinear") -> np.ndarray:
    """``image_prev`` [H', W', C] read at ``xy_prev`` [H, W, 2] (pixel coordinates of that image), bilinearly,
    with ``kernel="catmull_rom"``, or ``"nearest"`` (the pixel the spot falls in): [H, W, C] in its dtype, 0 where
    not ``valid``. Footprints: module docstring."""
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {', '.join(KERNELS)}, got {kernel!r}")
    img = _channels(image_prev)
    valid = np.asarray(valid, dtype=bool)
    h, w = img.shape[:2]
    if kernel == "nearest":             # every pixel read (an invalid one at pixel 0), then zeroed: no scatter
        xy = np.where(valid[..., None], np.asarray(xy_prev, dtype=np.float64), 0.5)
        if not np.all(np.isfinite(xy)):
            raise ValueError("xy_prev is not finite on a valid pixel")
        out = _flat(img).take((_pixel_of(xy[..., 1], h) * w + _pixel_of(xy[..., 0], w)).reshape(-1), axis=0)
        out = out.reshape(valid.shape + (img.shape[2],))
        out[~valid] = 0
        return out
    out = np.zeros(valid.shape + (img.shape[2],), dtype=img.dtype)
    if valid.any():
        xy = np.asarray(xy_prev)[valid].astype(np.float64)
        if not np.all(np.isfinite(xy)):
            raise ValueError("xy_prev is not finite on a valid pixel")
        if kernel == "bilinear":
            out[valid] = _read(img, _footprint(xy, w, h)).astype(img.dtype)
        else:
            out[valid] = np.maximum(_catmull_rom(img, xy), 0.0).astype(img.dtype)
    return out


def _pixel_of(coord: np.ndarray, size: int) -> np.ndarray:
    """The index of the pixel a continuous coordinate falls in (pixel i covers [i, i + 1)), clamped to the image."""
    return np.clip(np.floor(coord).astype(np.int64), 0, size - 1)


def _catmull_rom(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Catmull-Rom read of ``image`` [H, W, C] at ``xy`` [N, 2] (finite): [N, C] float64, the 4x4 taps around
    each point clamped at the border. The weights of offsets -1..2 at fraction f are a cubic in f that is
    (0, 1, 0, 0) at f = 0 and sums to 1."""
    h, w = image.shape[:2]
    u, v = xy[:, 0] - 0.5, xy[:, 1] - 0.5
    i0, j0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)

    def weights(f):
        return (f * (-0.5 + f * (1 - 0.5 * f)), 1 + f * f * (-2.5 + 1.5 * f), f * (0.5 + f * (2 - 1.5 * f)),
                f * f * (-0.5 + 0.5 * f))
    wx, wy = weights(u - i0), weights(v - j0)
    cols, pixels = [np.clip(i0 + dx - 1, 0, w - 1) for dx in range(4)], _flat(image)
    out = np.zeros((xy.shape[0], image.shape[2]))
    for dy in range(4):
        rows = np.clip(j0 + dy - 1, 0, h - 1) * w
        for dx in range(4):             # a float32 image is widened to float64 by the product itself
            out += (wx[dx] * wy[dy])[:, None] * pixels.take(rows + cols[dx], axis=0)
    return out


@dataclass(frozen=True, eq=False)
class View:
    """What reprojection needs of one frame: its camera and depth (H, W), or its motion vectors (H, W, 4,
    ``flow``), and its shading normal (H, W, 3) (None: no normal test)."""
    camera: Camera | None
    depth: np.ndarray | None
    normal: np.ndarray | None = None
    motion: np.ndarray | None = None

    @classmethod
    def of(cls, camera: Camera, buffers: dict[str, np.ndarray]) -> View:
        """The view of a frame's buffers (``depth`` (H, W, 1), ``normal`` where present) seen by ``camera``."""
        return cls(camera, buffers["depth"][..., 0], buffers.get("normal"))


def linked(view: View, view_prev: View) -> str | None:
    """How ``view``'s pixels are followed into ``view_prev``: "motion" (both frames have motion vectors: the
    renderer's own, moving objects included), "camera" (both have a camera and depth: a static scene) or None."""
    if view.motion is not None and view_prev.motion is not None:
        return "motion"
    if all(v.camera is not None and v.depth is not None for v in (view, view_prev)):
        return "camera"
    return None


def reproject_view(view: View, view_prev: View, world: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where ``view``'s pixels were in ``view_prev``: ``flow`` or ``reproject`` (with both frames' normals, and
    ``world``, the points ``view`` sees, where the caller has them), as ``linked`` says; ValueError when the two
    frames share neither motion vectors nor cameras with depth."""
    how = linked(view, view_prev)
    if how == "motion":
        return flow(view.motion, view_prev.motion, depth_t=view.depth, depth_prev=view_prev.depth)
    if how == "camera":
        return reproject(view.depth, view.camera, view_prev.camera, depth_prev=view_prev.depth,
                         normal_t=view.normal, normal_prev=view_prev.normal, world_t=world)
    raise ValueError("the two frames share neither motion vectors nor cameras with depth")


def turned(view: View) -> View:
    """``view`` with its motion's two halves exchanged (``to_next`` first): followed with it, ``flow`` leads into
    the frame after, and the frame after's turned motion tests the way back."""
    if view.motion is None:
        return view
    return View(view.camera, view.depth, view.normal, np.concatenate([view.motion[..., 2:], view.motion[..., :2]], -1))


def trace(view: View, past: list[View], ahead: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
    """Where ``view``'s pixels were in each frame of ``past`` (the frames before it, the latest first): a list of
    (xy [H, W, 2], valid [H, W]) as ``reproject_view`` gives for the previous frame, as long as the frames stay
    linked (``linked``), which may be shorter than ``past``. Cameras with depth: each frame directly; motion
    vectors: chained (module docstring, "Further back"). ``ahead``: ``past`` are the frames after it, the next
    first, and the answer is where its pixels will be in them."""
    if ahead:
        view, past = turned(view), [turned(v) for v in past]
    found: list[tuple[np.ndarray, np.ndarray]] = []
    newer, world = view, None
    for older in past:
        how = linked(view, older) if view.motion is None else linked(newer, older)
        if how is None:
            break
        if how == "camera":                 # the points frame t sees, unprojected once for every frame
            world = unproject(view.depth, view.camera) if world is None else world
            found.append(reproject_view(view, older, world))
        elif not found:
            found.append(reproject_view(newer, older))
        else:
            xy, valid = found[-1]
            step_xy, step_valid = reproject_view(newer, older)
            h, w = step_valid.shape
            xy, valid = xy.astype(np.float64), valid.copy()
            idx = np.nonzero(valid)
            if idx[0].size:
                offset = np.where(np.isfinite(step_xy), step_xy - pixel_centres(w, h), 0.0)
                spot = xy[idx]
                xy[idx] = spot + _read(offset, _footprint(spot, w, h))
                valid[idx] = step_valid.reshape(-1).take(_pixel_of(spot[:, 1], h) * w + _pixel_of(spot[:, 0], w))
                with np.errstate(invalid="ignore"):
                    valid &= (xy[..., 0] >= 0) & (xy[..., 0] <= w) & (xy[..., 1] >= 0) & (xy[..., 1] <= h)
            xy[~valid] = np.nan
            found.append((xy.astype(np.float32), valid))
        newer = older
    return found


def warp_previous(image_prev: np.ndarray, view: View, view_prev: View,
                  traced: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(``image_prev``, an image of the previous frame, brought into this one (H, W, C) float32, the (H, W) bool
    validity): followed with ``reproject_view`` (or ``traced``, what it gave for these two views before), read
    with the Catmull-Rom kernel on the tonemapped image x / (1 + x) and brought back to radiance, no brighter than
    the image's brightest pixel (module docstring), 0 where invalid (disocclusions, silhouettes, background, off
    screen)."""
    xy, valid = reproject_view(view, view_prev) if traced is None else traced
    toned = reinhard(np.asarray(image_prev, np.float64))
    read = np.minimum(warp(toned, xy, valid, kernel="catmull_rom"), toned.max(initial=0.0))
    return inverse_reinhard(read).astype(np.float32), valid


# ---- the cameras in files --------------------------------------------------------------------

def camera_record(cam: Camera) -> dict:
    """The camera fields of a frame's ``frame.json`` besides width and height (``camera_from_record`` reads
    them back): the pose rounded to 6 decimals (Mitsuba holds it in float32, relative 6e-8), the field of
    view and the clip distances."""
    return {"camera_to_world": np.round(cam.camera_to_world, 6).tolist(), "fov_x": float(cam.fov_x),
            "near_clip": float(cam.near), "far_clip": float(cam.far)}


def camera_from_record(record: dict, where: str = "frame.json") -> Camera:
    """The camera of a frame record (``frame.json``); StoreError naming ``where`` and what is missing
    (frames rendered before the field of view was recorded have ``camera_to_world`` but no ``fov_x``)."""
    missing = [k for k in ("camera_to_world", "fov_x", "width", "height") if k not in record]
    if missing:
        raise StoreError(f"{where}: no camera: key {', '.join(map(repr, missing))} missing (frames rendered before "
                         "cameras were recorded lack 'fov_x'; render the frame again)")
    try:
        return Camera(np.asarray(record["camera_to_world"], dtype=np.float64), float(record["fov_x"]),
                      record["width"], record["height"], float(record.get("near_clip", NEAR_CLIP)),
                      float(record.get("far_clip", FAR_CLIP)))
    except (TypeError, ValueError) as exc:
        raise StoreError(f"{where}: the recorded camera is not usable ({exc})") from None


def exr_matrices(cam: Camera) -> dict[str, np.ndarray]:
    """The OpenEXR header attributes ``worldToCamera`` and ``worldToNDC`` of ``cam``: float32 4x4 in Imath's
    row-vector convention (p' = p M), i.e. the transposes of the column-vector matrices."""
    world_to_camera = cam.world_to_camera()
    # C order: OpenEXR's binding copies the buffer as it lies in memory, whatever the strides say.
    return {"worldToCamera": np.ascontiguousarray((_FLIP_X @ world_to_camera).T, dtype=np.float32),
            "worldToNDC": np.ascontiguousarray((_ndc_projection(cam) @ world_to_camera).T, dtype=np.float32)}


def _ndc_projection(cam: Camera) -> np.ndarray:
    """Column-vector matrix from Mitsuba's local camera frame to homogeneous NDC (w = z)."""
    t, aspect = cam.tan_half, cam.width / cam.height
    near, far = cam.near, cam.far
    a, b = (1.0, -near) if math.isinf(far) else (far / (far - near), -near * far / (far - near))
    return np.array([[-0.5 / t, 0, 0.5, 0], [0, -0.5 * aspect / t, 0.5, 0], [0, 0, a, b], [0, 0, 1, 0]])


def camera_from_exr(world_to_camera, world_to_ndc, width: int, height: int, where: str = "EXR header") -> Camera:
    """The camera of an image whose header has ``worldToCamera`` and ``worldToNDC`` (row-vector 4x4, as
    ``exr_matrices`` writes them) and whose display window is ``width`` x ``height``. StoreError naming
    ``where`` when the matrices are not a rigid camera with a centred pinhole projection of square pixels.
    near and far come from NDC z when it maps them to 0 and 1 (as written here), else 0 and infinity."""
    wtc = np.asarray(world_to_camera, dtype=np.float64).T
    wtn = np.asarray(world_to_ndc, dtype=np.float64).T
    if wtc.shape != (4, 4) or wtn.shape != (4, 4) or not (np.isfinite(wtc).all() and np.isfinite(wtn).all()):
        raise StoreError(f"{where}: worldToCamera and worldToNDC must be finite 4x4 matrices")
    try:
        c2w = np.linalg.inv(wtc) @ _FLIP_X
    except np.linalg.LinAlgError:
        raise StoreError(f"{where}: worldToCamera is singular") from None
    if not np.allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-4) or not np.allclose(c2w[3], [0, 0, 0, 1], atol=1e-5):
        raise StoreError(f"{where}: worldToCamera is not a rigid transform (rotation and translation)")
    p = wtn @ c2w                       # homogeneous NDC from Mitsuba's local frame
    if abs(p[3, 2]) < 1e-12:
        raise StoreError(f"{where}: worldToNDC is not a perspective projection (w does not depend on z)")
    p = p / p[3, 2]
    scale = 1e-4 * max(1.0, float(np.abs(p[:2, :3]).max()))
    t = -0.5 / p[0, 0] if p[0, 0] < 0 else math.nan
    expect = np.array([[-0.5 / t, 0, 0.5], [0, -0.5 * (width / height) / t, 0.5]]) if t > 0 else None
    if (expect is None or not np.allclose(p[:2, :3], expect, atol=scale) or not np.allclose(p[:2, 3], 0, atol=scale)
            or not np.allclose(p[3], [0, 0, 1, 0], atol=1e-6)):
        raise StoreError(f"{where}: worldToNDC is not a centred pinhole projection with square pixels of a "
                         f"{width}x{height} image (the only cameras supported)")
    a, b = p[2, 2], p[2, 3]
    near = -b / a if a > 0 else math.nan
    far = b / (1 - a) if a < 1 else math.inf
    if not (near >= 0 and far > near):
        near, far = 0.0, math.inf
    try:
        return Camera(c2w, math.degrees(2 * math.atan(t)), width, height, float(near), float(far))
    except ValueError as exc:
        raise StoreError(f"{where}: {exc}") from None
