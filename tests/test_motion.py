"""pipeline.motion: projection, reprojection and warping against analytic answers; the cameras in
frame.json and in the EXR headers; warping real renders of the tiny store."""
import json
import math

import numpy as np
import pytest

from mcdenoise.pipeline import motion
from mcdenoise.pipeline.errors import StoreError
from mcdenoise.pipeline.exr import read_camera, scan_exr, write_image
from mcdenoise.pipeline.motion import Camera, project, reproject, unproject, warp
from tests.helpers import look_at

W, H = 64, 48
FOV = 50.0


def camera(origin=(0, 0, 0), target=(0, 0, -1), up=(0, 1, 0), fov=FOV, width=W, height=H) -> Camera:
    return Camera(look_at(origin, target, up), fov, width, height)


def plane_depth(cam: Camera, normal, offset) -> np.ndarray:
    """Camera-space z at every pixel centre of the plane normal . X = offset, by intersecting each pixel
    centre's ray (direction per unit z, from the pinhole model of the module docstring) with the plane."""
    j, i = np.mgrid[0:cam.height, 0:cam.width] + 0.5
    t = math.tan(math.radians(cam.fov_x) / 2)
    local = np.stack([(1 - 2 * i / cam.width) * t, (cam.height / 2 - j) * 2 / cam.width * t, np.ones_like(i)], -1)
    d = local @ cam.camera_to_world[:3, :3].T
    o = cam.camera_to_world[:3, 3]
    n = np.asarray(normal, float)
    return (offset - n @ o) / (d @ n)


def pixel_of_direction(local_dir: np.ndarray, width=W, height=H, fov=FOV) -> np.ndarray:
    """Pixel coordinates of a direction in a camera's local frame (x left, y up, z forward)."""
    t = math.tan(math.radians(fov) / 2)
    x, y, z = local_dir[..., 0], local_dir[..., 1], local_dir[..., 2]
    return np.stack([width / 2 * (1 - x / (z * t)), height / 2 - width / 2 * y / (z * t)], -1)


def test_round_trip_project_unproject():
    cam = camera(origin=(0.3, 1.2, 4.0), target=(0, 0.5, 0))
    depth = np.random.default_rng(0).uniform(0.5, 20, (H, W))
    xy, z = project(unproject(depth, cam), cam)
    # float64 throughout: a 4x4 inverse and a division, round-off of order 1e-15 relative.
    np.testing.assert_allclose(xy, motion.pixel_centres(W, H), atol=1e-9)
    np.testing.assert_allclose(z, depth, rtol=1e-12)


def test_translation_over_a_fronto_parallel_plane_shifts_by_the_disparity():
    """Camera moves by b to its left in front of a plane at distance D: every point moves by
    b f / D pixels, f = W / (2 tan(fov/2)) the focal length in pixels, to the left in frame t-1."""
    D, b = 5.0, 0.2
    prev = camera(origin=(0, 0, 0), target=(0, 0, -1))
    cur = camera(origin=(-b, 0, 0), target=(-b, 0, -1))   # looking down -z, left is -x
    assert np.allclose(cur.camera_to_world[:3, 0], [-1, 0, 0])
    depth = plane_depth(cur, (0, 0, 1), -D)
    np.testing.assert_allclose(depth, D)
    xy, valid = reproject(depth, cur, prev, depth_prev=plane_depth(prev, (0, 0, 1), -D))
    shift = b * W / (2 * math.tan(math.radians(FOV) / 2)) / D
    expected = motion.pixel_centres(W, H) - [shift, 0]
    on = expected[..., 0] >= 0
    assert np.abs(xy - expected)[on].max() < 0.01
    # Off-screen: the columns that land left of frame t-1 are masked, and only they.
    np.testing.assert_array_equal(valid, on)
    assert (~on).sum() == H * math.ceil(shift - 0.5)


def test_rotation_over_a_slanted_plane():
    """Camera turns by 6 degrees about its up axis in front of a slanted plane: a pure rotation maps
    directions, so frame t-1's pixel is the direction rotated back, whatever the depth."""
    theta = math.radians(6)
    prev = camera()
    target = (math.sin(theta), 0, -math.cos(theta))       # turned to the right (towards +x)
    cur = camera(target=target)
    normal = np.array([0.3, 0.8, 1.0]) / np.linalg.norm([0.3, 0.8, 1.0])
    depth = plane_depth(cur, normal, -6.0)
    assert (depth > 0).all()
    xy, valid = reproject(depth, cur, prev, depth_prev=plane_depth(prev, normal, -6.0))
    j, i = np.mgrid[0:H, 0:W] + 0.5
    t = math.tan(math.radians(FOV) / 2)
    local_t = np.stack([(1 - 2 * i / W) * t, (H / 2 - j) * 2 / W * t, np.ones_like(i)], -1)
    world_dir = local_t @ cur.camera_to_world[:3, :3].T
    expected = pixel_of_direction(world_dir @ prev.camera_to_world[:3, :3])
    inside = (expected[..., 0] >= 0) & (expected[..., 0] <= W) & (expected[..., 1] >= 0) & (expected[..., 1] <= H)
    err = np.abs(xy - expected)[inside].max()
    assert err < 0.01, err
    np.testing.assert_array_equal(valid, inside)
    assert 0 < (~inside).sum() < W * H / 4


def box_scene(cam: Camera, box_z=-4.0, plane_z=-10.0, half=(0.6, 0.5)) -> np.ndarray:
    """Depth of a fronto-parallel square (|x| <= half[0], |y| <= half[1] at z = box_z) in front of the
    plane z = plane_z, for a camera looking down -z."""
    near = plane_depth(cam, (0, 0, 1), box_z)
    j, i = np.mgrid[0:cam.height, 0:cam.width] + 0.5
    t = math.tan(math.radians(cam.fov_x) / 2)
    local = np.stack([(1 - 2 * i / cam.width) * t, (cam.height / 2 - j) * 2 / cam.width * t, np.ones_like(i)], -1)
    hit = cam.camera_to_world[:3, 3] + near[..., None] * (local @ cam.camera_to_world[:3, :3].T)
    on_box = (np.abs(hit[..., 0]) <= half[0]) & (np.abs(hit[..., 1]) <= half[1])
    return np.where(on_box, near, plane_depth(cam, (0, 0, 1), plane_z)), on_box


def test_disocclusion_behind_a_box_is_masked():
    """A box 4 in front of a plane 10 away; the camera moves 0.5 to the right. The plane points frame t
    sees that the box hid from frame t-1 must be invalid; every other point is valid, except those
    whose bilinear footprint in t-1 straddles the box's silhouette (within a pixel of it)."""
    b = 0.5
    prev = camera(origin=(0, 0, 0), target=(0, 0, -1))
    cur = camera(origin=(b, 0, 0), target=(b, 0, -1))
    depth_t, box_t = box_scene(cur)
    depth_p, _ = box_scene(prev)
    xy, valid = reproject(depth_t, cur, prev, depth_prev=depth_p)
    # Analytic occlusion: the plane point X is hidden from the t-1 camera (at the origin) when the
    # segment to it crosses z = -4 inside the box: at X * 4 / 10.
    world = unproject(depth_t, cur)
    crossing = world * (4.0 / 10.0)
    hidden = ~box_t & (np.abs(crossing[..., 0]) <= 0.6) & (np.abs(crossing[..., 1]) <= 0.5)
    assert hidden.sum() > 20
    assert not valid[hidden].any()
    # The box's silhouette in t-1: |x| = 0.6, |y| = 0.5 at depth 4, in pixels.
    f = W / (2 * math.tan(math.radians(FOV) / 2))
    edges_x = W / 2 + np.array([-0.6, 0.6]) / 4 * f
    edges_y = H / 2 + np.array([-0.5, 0.5]) / 4 * f
    near_edge = ((np.abs(xy[..., 0, None] - edges_x) < 1).any(-1) & (xy[..., 1] > edges_y[0] - 1)
                 & (xy[..., 1] < edges_y[1] + 1)) | ((np.abs(xy[..., 1, None] - edges_y) < 1).any(-1)
                                                     & (xy[..., 0] > edges_x[0] - 1) & (xy[..., 0] < edges_x[1] + 1))
    on_screen = (xy[..., 0] >= 0) & (xy[..., 0] <= W)
    must_be_valid = on_screen & ~hidden & ~near_edge
    assert must_be_valid.sum() > 0.8 * W * H
    assert valid[must_be_valid].all()
    # The band left out along the silhouette is at most the footprint's width: fewer pixels than
    # 2 pixels along the perimeter.
    assert (on_screen & ~hidden & ~valid).sum() <= 2 * 2 * (np.ptp(edges_x) + np.ptp(edges_y))


def test_background_and_disagreeing_normals_are_invalid():
    cam = camera()
    depth = plane_depth(cam, (0, 0, 1), -5.0)
    depth[:, :10] = 0                                      # background
    normal = np.broadcast_to(np.array([0, 0, 1.0]), (H, W, 3)).copy()
    other = normal.copy()
    other[20:30] = [1.0, 0, 0]                             # frame t-1 sees another orientation there
    xy, valid = reproject(depth, cam, cam, depth_prev=depth, normal_t=normal, normal_prev=other)
    assert np.isnan(xy[:, :10]).all() and not valid[:, :10].any()
    assert not valid[20:30].any()
    # Rows 19 and 30 land on pixel centres: their footprints hold only their own row.
    assert valid[:20, 10:].all() and valid[30:, 10:].all()


def test_identity_warp_returns_the_image_exactly():
    cam = camera(origin=(1, 2, 3), target=(0, 0, 0))
    depth = plane_depth(cam, (0, 1, 0), -1.0)
    depth[depth < 0] = 0
    image = np.random.default_rng(1).random((H, W, 3)).astype(np.float32)
    xy, valid = reproject(depth, cam, cam, depth_prev=depth)
    assert valid[depth > 0].all()
    out = warp(image, xy, valid)
    np.testing.assert_array_equal(out[valid], image[valid])
    assert (out[~valid] == 0).all()


def test_warp_is_bilinear_and_clamped_at_the_border():
    image = np.arange(4 * 5, dtype=np.float64).reshape(4, 5, 1)     # value = 5 row + column
    xy = np.array([[[1.75, 2.25], [0.1, 0.2], [4.9, 3.9]]])
    out = warp(image, xy, np.ones((1, 3), bool))
    # A linear image is reproduced by bilinear interpolation; the border clamps to the edge centres.
    np.testing.assert_allclose(out[0, :, 0], [5 * 1.75 + 1.25, 0.0, 5 * 3 + 4])


def test_reads_of_a_wide_image_equal_numpy_row_column_indexing():
    # The reads index the flattened image (row * width + column): on an image wider than tall, with spots all over
    # it, the border and past it, every kernel gives what indexing rows and columns apart gives, to the bit.
    rng = np.random.default_rng(9)
    image = rng.random((5, 9, 3)).astype(np.float32)
    xy = rng.uniform(-1.0, 10.0, (4, 6, 2)) * [1.0, 0.6]
    valid = rng.random((4, 6)) < 0.8
    xy[~valid] = np.nan                                      # invalid spots may be anything, NaN included
    h, w = image.shape[:2]
    pts = xy[valid]
    col = np.clip(np.floor(pts[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.floor(pts[:, 1]).astype(int), 0, h - 1)
    out = warp(image, xy, valid, kernel="nearest")
    np.testing.assert_array_equal(out[valid], image[row, col])
    np.testing.assert_array_equal(out[~valid], 0)
    u, v = np.clip(pts[:, 0] - 0.5, 0, w - 1), np.clip(pts[:, 1] - 0.5, 0, h - 1)
    i0, j0 = np.minimum(np.floor(u).astype(int), w - 2), np.minimum(np.floor(v).astype(int), h - 2)
    fx, fy = (u - i0)[:, None], (v - j0)[:, None]
    px = image.astype(np.float64)
    expected = ((1 - fx) * (1 - fy) * px[j0, i0] + fx * (1 - fy) * px[j0, i0 + 1] + (1 - fx) * fy * px[j0 + 1, i0]
                + fx * fy * px[j0 + 1, i0 + 1])
    np.testing.assert_allclose(warp(image, xy, valid)[valid], expected, rtol=1e-6, atol=1e-7)
    cr = warp(image, xy, valid, kernel="catmull_rom")[valid]
    for k, spot in enumerate(pts):
        i, j = math.floor(spot[0] - 0.5), math.floor(spot[1] - 0.5)
        wx, wy = (_catmull_rom_weights(spot[0] - 0.5 - i), _catmull_rom_weights(spot[1] - 0.5 - j))
        ref = sum(wx[a] * wy[b] * px[min(max(j + b - 1, 0), h - 1), min(max(i + a - 1, 0), w - 1)]
                  for a in range(4) for b in range(4))
        np.testing.assert_allclose(cr[k], np.maximum(ref, 0), rtol=1e-6, atol=1e-7)
    xy[valid.nonzero()[0][0], valid.nonzero()[1][0]] = np.nan
    for kernel in motion.KERNELS:
        with pytest.raises(ValueError, match="not finite on a valid pixel"):
            warp(image, xy, valid, kernel=kernel)


def _catmull_rom_weights(f: float) -> list[float]:
    """The Catmull-Rom weights of offsets -1..2 at fraction f, from the kernel's definition (|x| < 1:
    1.5|x|^3 - 2.5|x|^2 + 1; 1 <= |x| < 2: -0.5|x|^3 + 2.5|x|^2 - 4|x| + 2)."""
    def k(x):
        x = abs(x)
        return 1.5 * x**3 - 2.5 * x**2 + 1 if x < 1 else (-0.5 * x**3 + 2.5 * x**2 - 4 * x + 2 if x < 2 else 0.0)
    return [k(f + 1), k(f), k(f - 1), k(f - 2)]


def test_every_channel_and_dot_are_numpys_reductions():
    rng = np.random.default_rng(3)
    mask = rng.random((6, 7, 3)) < 0.9
    np.testing.assert_array_equal(motion.every_channel(mask), mask.all(axis=-1))
    np.testing.assert_array_equal(motion.every_channel(mask[..., :2]), mask[..., :2].all(axis=-1))
    a, b = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    np.testing.assert_array_equal(motion._dot(a, b), (a * b).sum(axis=-1))


def _raw_catmull_rom(image, xy) -> float:
    return float(motion._catmull_rom(image, np.asarray(xy, float)[None])[0, 0])


def test_catmull_rom_reads_centres_and_linear_images_exactly_and_is_sharper():
    rng = np.random.default_rng(4)
    image = rng.random((6, 7, 2)).astype(np.float32)
    centres = motion.pixel_centres(7, 6)
    # on pixel centres the kernel is (0, 1, 0, 0): each pixel alone, to the bit
    np.testing.assert_array_equal(warp(image, centres, np.ones((6, 7), bool), kernel="catmull_rom"), image)
    # a linear ramp (away from the clamped border) is reproduced: the weights sum to 1 and have no linear error
    ramp = (5.0 * np.arange(7)[None, :] + 3.0 * np.arange(6)[:, None] + 1.0)[..., None]
    xy = np.array([[[2.3, 3.1], [3.5, 2.5], [4.9, 2.05]]])
    out = warp(ramp, xy, np.ones((1, 3), bool), kernel="catmull_rom")[0, :, 0]
    np.testing.assert_allclose(out, 5 * (xy[0, :, 0] - 0.5) + 3 * (xy[0, :, 1] - 0.5) + 1, rtol=1e-12)
    # across a step 0 | 1 between columns 2 and 3: both read 0.5 midway; a quarter pixel towards the dark side
    # bilinear reads 0.25, Catmull-Rom w2 + w3 at f = 1/4 = 0.2265625 - 0.0234375 (sharper); just beyond the
    # step its negative lobe would read below 0, and the read is set to 0
    step = np.zeros((3, 6, 1))
    step[:, 3:] = 1.0
    at = np.array([[[3.0, 1.5], [2.75, 1.5], [1.75, 1.5]]])
    cr = warp(step, at, np.ones((1, 3), bool), kernel="catmull_rom")[0, :, 0]
    bl = warp(step, at, np.ones((1, 3), bool))[0, :, 0]
    np.testing.assert_allclose(cr, [0.5, 0.203125, 0.0])
    np.testing.assert_allclose(bl, [0.5, 0.25, 0.0])
    assert _raw_catmull_rom(step, at[0, 2]) < 0                 # the lobe that was set to 0
    with pytest.raises(ValueError, match="kernel"):
        warp(step, at, np.ones((1, 3), bool), kernel="lanczos")


def test_the_history_is_read_on_tonemapped_values_so_a_small_light_stays_out_of_its_neighbours():
    """``warp_previous`` reads x / (1 + x) with Catmull-Rom and brings it back: a one-pixel light of radiance 200 on
    a floor of 0.2, read 0.4 pixel to the right, gives its left neighbour T^-1 of the Catmull-Rom mix of T values
    (about 1.07; read on radiance, about 85)."""
    image = np.full((5, 7, 3), 0.2, np.float32)
    image[2, 3] = 200.0
    xy = motion.pixel_centres(7, 5) + np.array([0.4, 0.0])
    valid = np.ones((5, 7), bool)
    got, kept = motion.warp_previous(image, None, None, (xy, valid))
    assert got.dtype == np.float32 and kept is valid
    t = lambda x: x / (1.0 + x)                                     # noqa: E731
    w = _catmull_rom_weights(0.4)                                   # taps at columns 1, 2, 3 (the light), 4
    toned = w[0] * t(0.2) + w[1] * t(0.2) + w[2] * t(200.0) + w[3] * t(0.2)
    np.testing.assert_allclose(got[2, 2], toned / (1.0 - toned), rtol=1e-6)
    assert 0.2 < got[2, 2, 0] < 1.1 < 50.0 < warp(image, xy, valid, kernel="catmull_rom")[2, 2, 0]
    np.testing.assert_allclose(got[0], 0.2, rtol=1e-6)                 # far from the light, the floor
    # past a step 0.2 | 200 the kernel overshoots the bright side; on x / (1 + x) too, so the read is capped at the
    # image's brightest value (on radiance it would read above it)
    step = np.full((5, 7, 3), 0.2, np.float32)
    step[:, 3:] = 200.0
    at = motion.pixel_centres(7, 5) + np.array([0.25, 0.0])
    over = warp(step, at, valid, kernel="catmull_rom")[2, 3, 0]
    capped, _ = motion.warp_previous(step, None, None, (at, valid))
    assert over > 200.0 and capped.max() == np.float32(200.0) and capped[2, 3, 0] == np.float32(200.0)
    # a constant image is read back at any offset, to float32 rounding (the weights sum to 1)
    flat, _ = motion.warp_previous(np.full((5, 7, 3), 3.7, np.float32), None, None, (xy + 0.13, valid))
    np.testing.assert_allclose(flat, 3.7, rtol=4e-7)


# ---- motion vectors (a renderer's own) ----------------------------------------------------------

def blender_vector_pass(cam_t: Camera, depth_t, cam_prev: Camera, depth_prev) -> tuple[np.ndarray, np.ndarray]:
    """The Vector passes Cycles would write for frames t-1 and t of a static scene (its convention, in raster
    coordinates with y up: X, Y = where the point was in the previous frame minus where it is; Z, W = where it
    is minus where it will be), built from the cameras: (frame t's pass, frame t-1's pass), (H, W, 4)."""
    centres = motion.pixel_centres(W, H)
    to_prev = project(unproject(depth_t, cam_t), cam_prev)[0] - centres      # in y-down pixels
    to_next = project(unproject(depth_prev, cam_prev), cam_t)[0] - centres
    up = np.array([1.0, -1.0])                                                # y down -> y up
    zeros = np.zeros((H, W, 2))
    return (np.concatenate([to_prev * up, zeros], -1).astype(np.float32),
            np.concatenate([zeros, -to_next * up], -1).astype(np.float32))


def test_motion_vectors_give_the_reprojection_of_a_translating_camera():
    D, b = 5.0, 0.2
    prev = camera(origin=(0, 0, 0), target=(0, 0, -1))
    cur = camera(origin=(-b, 0.5 * b, 0), target=(-b, 0.5 * b, -1))
    depth_t, depth_p = plane_depth(cur, (0, 0, 1), -D), plane_depth(prev, (0, 0, 1), -D)
    vec_t, vec_p = blender_vector_pass(cur, depth_t, prev, depth_p)
    xy, valid = motion.flow(motion.from_blender_vectors(vec_t), motion.from_blender_vectors(vec_p))
    xy_cam, valid_cam = reproject(depth_t, cur, prev, depth_prev=depth_p)
    # the vectors are float32 (relative 6e-8 of a few pixels): the same landing spots and the same mask
    assert np.abs(xy - xy_cam).max() < 1e-4
    np.testing.assert_array_equal(valid, valid_cam)
    assert 0 < (~valid).sum() < W * H / 4                        # the columns and rows that leave the frame


def test_motion_vectors_mask_a_disocclusion():
    """The box scene of the depth test: the forward-backward test masks what the box hid in frame t-1, as the
    depth test does, and keeps every pixel whose footprint lies on one surface."""
    b = 0.5
    prev = camera(origin=(0, 0, 0), target=(0, 0, -1))
    cur = camera(origin=(b, 0, 0), target=(b, 0, -1))
    (depth_t, box_t), (depth_p, _) = box_scene(cur), box_scene(prev)
    vec_t, vec_p = blender_vector_pass(cur, depth_t, prev, depth_p)
    xy, valid = motion.flow(motion.from_blender_vectors(vec_t), motion.from_blender_vectors(vec_p))
    xy_cam, valid_cam = reproject(depth_t, cur, prev, depth_prev=depth_p)
    assert np.abs(xy - xy_cam).max() < 1e-4
    world = unproject(depth_t, cur)
    crossing = world * (4.0 / 10.0)
    hidden = ~box_t & (np.abs(crossing[..., 0]) <= 0.6) & (np.abs(crossing[..., 1]) <= 0.5)
    assert hidden.sum() > 20 and not valid[hidden].any()
    # The box moves b f (1/4 - 1/10) = 5.1 pixels more than the plane: a footprint whose taps on the other
    # surface weigh more than 0.5 / 5.1 fails the test, a lighter one passes. So the two masks may differ
    # within a pixel of the silhouettes, and nowhere else.
    f = W / (2 * math.tan(math.radians(FOV) / 2))
    edges_x = W / 2 + np.array([-0.6, 0.6]) / 4 * f
    edges_y = H / 2 + np.array([-0.5, 0.5]) / 4 * f
    near_edge = (((np.abs(xy_cam[..., 0, None] - edges_x) < 1).any(-1) & (xy_cam[..., 1] > edges_y[0] - 1)
                  & (xy_cam[..., 1] < edges_y[1] + 1)) | ((np.abs(xy_cam[..., 1, None] - edges_y) < 1).any(-1)
                                                          & (xy_cam[..., 0] > edges_x[0] - 1)
                                                          & (xy_cam[..., 0] < edges_x[1] + 1)))
    assert valid[valid_cam & ~near_edge].all() and not valid[~valid_cam & ~near_edge].any()


def test_blender_vector_pass_convention():
    """A point that moves right by 2 pixels and down by 1 per frame (rows top-down): Cycles writes X, Y = -2, +1
    (the previous position minus this one, y up) and Z, W = -2, +1 (this one minus the next)."""
    raw = np.broadcast_to(np.array([-2.0, 1.0, -2.0, 1.0], np.float32), (3, 4, 4))
    m = motion.from_blender_vectors(raw)
    np.testing.assert_array_equal(m[0, 0], [-2, -1, 2, 1])         # to_prev: left and up; to_next: right and down
    xy, valid = motion.flow(m, m)
    np.testing.assert_array_equal(xy[2, 3], [3.5 - 2, 2.5 - 1])
    # the pixels whose point was off frame t-1: the first two columns and the first row
    np.testing.assert_array_equal(valid, np.pad(np.ones((2, 2), bool), ((1, 0), (2, 0))))
    with pytest.raises(ValueError, match=r"\(H, W, 4\)"):
        motion.from_blender_vectors(raw[..., :2])
    # a non-finite vector (a damaged pass) follows nothing; a non-finite vector of frame t-1 fails the way back
    bad = m.copy()
    bad[2, 3, 0] = np.nan
    bad_prev = m.copy()
    bad_prev[0, 0, 2] = np.inf                   # row 0, column 0 of frame t-1: where row 1, column 2 of t was
    xy, valid = motion.flow(bad, bad_prev)
    assert np.isnan(xy[2, 3]).all()
    np.testing.assert_array_equal(np.argwhere(valid), [[1, 3], [2, 2]])


def test_views_link_by_motion_vectors_first_then_by_cameras():
    cam = camera()
    depth = plane_depth(cam, (0, 0, 1), -5.0)
    still = np.zeros((H, W, 4), np.float32)
    by_camera, by_motion = motion.View(cam, depth), motion.View(None, None, motion=still)
    both = motion.View(cam, depth, motion=still)
    assert motion.linked(by_camera, by_camera) == "camera"
    assert motion.linked(by_motion, by_motion) == motion.linked(both, by_motion) == "motion"
    assert motion.linked(by_motion, by_camera) is None
    with pytest.raises(ValueError, match="share neither"):
        motion.reproject_view(by_motion, by_camera)


def cycles_passes(cams: list[Camera], depths: list[np.ndarray]) -> list[np.ndarray]:
    """Our motion (``from_blender_vectors`` of the Vector pass Cycles would write) of each frame of a static scene
    seen by ``cams`` in order: to_prev into the frame before, to_next into the frame after (0 at the two ends)."""
    centres = motion.pixel_centres(W, H)
    out = []
    for k, (cam, depth) in enumerate(zip(cams, depths)):
        world = unproject(depth, cam)
        to_prev = project(world, cams[k - 1])[0] - centres if k > 0 else np.zeros((H, W, 2))
        to_next = project(world, cams[k + 1])[0] - centres if k + 1 < len(cams) else np.zeros((H, W, 2))
        out.append(np.concatenate([to_prev, to_next], -1).astype(np.float32))
    return out


def test_trace_reaches_each_past_frame_directly_with_cameras_and_by_a_chain_with_vectors():
    """Three frames of a camera translating over a plane slanted away from it (the shift varies across the
    image). Cameras: each past frame is reproject()'s answer between the two frames. Vectors: t -> t-1 -> t-2
    chained lands where the direct reprojection does, within the float32 vectors' round-off and the bilinear
    read of a smooth offset field (below 0.01 pixel), with the same mask away from the image border."""
    cams = [camera(origin=(-0.15 * k, 0.05 * k, 0), target=(-0.15 * k, 0.05 * k, -1)) for k in range(3)]
    normal = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])
    depths = [plane_depth(c, normal, -4.0) for c in cams]
    views = [motion.View(c, d) for c, d in zip(cams, depths)]
    found = motion.trace(views[2], [views[1], views[0]])
    for (xy, valid), k in zip(found, (1, 0)):
        direct = reproject(depths[2], cams[2], cams[k], depth_prev=depths[k])
        np.testing.assert_array_equal(xy, direct[0])
        np.testing.assert_array_equal(valid, direct[1])
    moving = [motion.View(None, None, motion=m) for m in cycles_passes(cams, depths)]
    chained = motion.trace(moving[2], [moving[1], moving[0]])
    assert len(chained) == 2
    np.testing.assert_array_equal(chained[0][1], motion.flow(moving[2].motion, moving[1].motion)[1])
    xy, valid = chained[1]
    xy_direct, valid_direct = reproject(depths[2], cams[2], cams[0], depth_prev=depths[0])
    both = valid & valid_direct
    assert both.sum() > 0.7 * W * H and np.abs(xy - xy_direct)[both].max() < 0.01
    # the masks differ only where a spot is within a pixel of frame t-2's border (half a pixel of chained error)
    near_border = ((xy_direct[..., 0] < 1) | (xy_direct[..., 0] > W - 1) | (xy_direct[..., 1] < 1)
                   | (xy_direct[..., 1] > H - 1))
    assert not ((valid != valid_direct) & ~near_border).any()
    assert np.isnan(xy[~valid]).all()


def test_trace_ahead_follows_the_vectors_forward_as_the_cameras_lead():
    """The three frames above, traced from the first into the two after it (``ahead``): with cameras each is
    reproject()'s answer; with vectors the chain t -> t+1 -> t+2 (``to_next``, tested by the next frame's
    ``to_prev``) lands where the direct reprojection does, within 0.01 pixel, with the same mask away from the
    border; traced backwards from the first frame's turned motion it is no longer the same (the test can fail)."""
    cams = [camera(origin=(-0.15 * k, 0.05 * k, 0), target=(-0.15 * k, 0.05 * k, -1)) for k in range(3)]
    normal = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])
    depths = [plane_depth(c, normal, -4.0) for c in cams]
    views = [motion.View(c, d) for c, d in zip(cams, depths)]
    for (xy, valid), k in zip(motion.trace(views[0], views[1:], ahead=True), (1, 2)):
        direct = reproject(depths[0], cams[0], cams[k], depth_prev=depths[k])
        np.testing.assert_array_equal(xy, direct[0])
        np.testing.assert_array_equal(valid, direct[1])
    moving = [motion.View(None, None, motion=m) for m in cycles_passes(cams, depths)]
    chained = motion.trace(moving[0], moving[1:], ahead=True)
    assert len(chained) == 2
    for (xy, valid), k in zip(chained, (1, 2)):
        xy_direct, valid_direct = reproject(depths[0], cams[0], cams[k], depth_prev=depths[k])
        both = valid & valid_direct
        assert both.sum() > 0.7 * W * H and np.abs(xy - xy_direct)[both].max() < 0.01
        near_border = ((xy_direct[..., 0] < 1) | (xy_direct[..., 0] > W - 1) | (xy_direct[..., 1] < 1)
                       | (xy_direct[..., 1] > H - 1))
        assert not ((valid != valid_direct) & ~near_border).any()
    # the first frame has no to_prev (zeros): followed backwards, every pixel stays put and fails the test
    assert not motion.trace(moving[0], moving[1:])[0][1].any()


def test_the_depth_test_refuses_a_disocclusion_the_forward_backward_test_lets_through():
    """A background at depth 10 moving 1.6 pixels right per frame behind an occluder at depth 2 (columns 0-7 of
    frame t-1) moving 1 pixel: pixel 9 of frame t (centre 9.5) was hidden at 7.9 in frame t-1, where the bilinear
    read of t-1's vectors (0.6 x 1.0 + 0.4 x 1.6) brings it back 0.36 pixel from where it started, inside the
    forward-backward tolerance. Its depth there (1 / (0.6 / 2 + 0.4 / 10) = 2.9 against 10) is refused; pixel 12
    (background in both frames) passes both tests; background (depth 0) has no depth to agree with."""
    h, w = 4, 16
    depth_prev = np.where(np.arange(w) < 8, 2.0, 10.0)[None, :].repeat(h, 0)
    depth_t = np.where(np.arange(w) < 9, 2.0, 10.0)[None, :].repeat(h, 0)
    motion_prev, motion_t = np.zeros((h, w, 4), np.float32), np.zeros((h, w, 4), np.float32)
    motion_prev[..., 2] = np.where(depth_prev < 5, 1.0, 1.6)         # t-1's to_next
    motion_t[..., 0] = np.where(depth_t < 5, -1.0, -1.6)             # t's to_prev
    _, loose = motion.flow(motion_t, motion_prev)
    _, tested = motion.flow(motion_t, motion_prev, depth_t=depth_t, depth_prev=depth_prev)
    assert loose[:, 9].all() and not tested[:, 9].any()
    assert loose[:, 12].all() and tested[:, 12].all()
    np.testing.assert_array_equal(tested, loose & ~(np.arange(w) == 9)[None, :])
    background = depth_t.copy()
    background[:, 12] = 0.0
    assert not motion.flow(motion_t, motion_prev, depth_t=background, depth_prev=depth_prev)[1][:, 12].any()


def test_trace_stops_where_the_frames_stop_being_linked():
    cam = camera()
    depth = plane_depth(cam, (0, 0, 1), -5.0)
    still = np.zeros((H, W, 4), np.float32)
    by_camera, by_motion = motion.View(cam, depth), motion.View(None, None, motion=still)
    assert len(motion.trace(by_camera, [by_camera, by_motion, by_camera])) == 1
    assert len(motion.trace(by_motion, [by_motion, by_camera])) == 1
    assert motion.trace(by_motion, [by_camera]) == []


def test_nearest_reads_the_pixel_the_spot_falls_in():
    image = np.arange(4 * 5 * 2, dtype=np.float32).reshape(4, 5, 2)
    xy = np.array([[[0.5, 0.5], [1.99, 0.01], [2.0, 3.5], [5.7, -0.2]]])       # the last one clamped
    valid = np.array([[True, True, True, False]])
    out = warp(image, xy, valid, kernel="nearest")
    np.testing.assert_array_equal(out[0, :3], [image[0, 0], image[0, 1], image[3, 2]])
    np.testing.assert_array_equal(out[0, 3], 0)
    xy[0, 3] = [5.7, -0.2]
    valid[0, 3] = True
    np.testing.assert_array_equal(warp(image, xy, valid, kernel="nearest")[0, 3], image[0, 4])
    with pytest.raises(ValueError, match="kernel must be one of"):
        warp(image, xy, valid, kernel="lanczos")


# ---- the cameras in files -----------------------------------------------------------------------

def test_header_matrices_map_a_world_point_to_its_pixel(tmp_path):
    """worldToNDC in the header (row vectors, p' = p M, then the homogeneous divide) sends a world
    point to the pixel project() gives; worldToCamera to RenderMan's camera space (x right)."""
    cam = camera(origin=(2.0, 1.5, 4.0), target=(0.2, 0.3, -0.5))
    black = np.zeros((H, W, 3), np.float32)
    write_image(tmp_path / "a.exr", {"color": black, "color.variance": black}, camera=cam)
    info = scan_exr(tmp_path / "a.exr")
    points = np.random.default_rng(2).uniform(-1, 1, (50, 3))
    xy, z = project(points, cam)
    homog = np.c_[points, np.ones(len(points))]
    ndc = homog @ info["matrices"]["worldToNDC"]
    pix = ndc[:, :2] / ndc[:, 3:] * [W, H]
    # float32 matrix entries (relative 6e-8) on coordinates of a few units: 1e-4 pixel is ample.
    np.testing.assert_allclose(pix, xy, atol=1e-4)
    cam_space = homog @ info["matrices"]["worldToCamera"]
    np.testing.assert_allclose(cam_space[:, 2], z, rtol=1e-5)
    right = W / 2 + cam_space[:, 0] / cam_space[:, 2] * W / (2 * cam.tan_half)
    np.testing.assert_allclose(right, xy[:, 0], atol=1e-4)   # x right in the image
    back = read_camera(tmp_path / "a.exr")
    np.testing.assert_allclose(back.camera_to_world, cam.camera_to_world, atol=1e-5)
    assert back.fov_x == pytest.approx(FOV, abs=1e-4) and (back.width, back.height) == (W, H)
    assert back.near == pytest.approx(cam.near, rel=1e-3)


def test_header_pixel_matches_mitsuba(tmp_path):
    """A small emitter at a known world point, rendered by Mitsuba through make_sensor: the centroid
    of its image is where the header matrix puts it (the conventions are Mitsuba's)."""
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba
    from mcdenoise.render.buffers import make_sensor
    from mcdenoise.render.frame import sensor_camera
    mi = import_mitsuba("llvm_ad_rgb")
    to_world = look_at((1.0, 0.7, 5.0), (0.1, 0.0, 0.0), (0, 1, 0))
    sensor = make_sensor(mi, mi.ScalarTransform4f(to_world), 40.0, W, H)
    cam = sensor_camera(mi, sensor)
    point = np.array([0.9, 0.45, 0.3])
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
                          "ball": {"type": "sphere", "center": point.tolist(), "radius": 0.08,
                                   "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}})
    img = np.asarray(mi.render(scene, sensor=sensor, spp=64), np.float64)[..., 0]
    j, i = np.mgrid[0:H, 0:W] + 0.5
    centroid = np.array([(img * i).sum(), (img * j).sum()]) / img.sum()
    xy, _ = project(point, cam)
    # The sphere's image is a disc of ~1.3 pixels radius, sampled at 64 spp with edge pixels partly
    # covered: its centroid lies within 0.05 pixel of the projected centre (a sphere's perspective
    # image is an ellipse whose centre is offset from the projected centre by r^2/d^2 terms, < 1e-3 px).
    assert np.abs(centroid - xy).max() < 0.05, (centroid, xy)


def test_camera_record_round_trip_and_old_frames():
    cam = camera(origin=(1, 2, 3), target=(0, 0, 0))
    record = {"width": W, "height": H, **motion.camera_record(cam)}
    assert list(record) == ["width", "height", "camera_to_world", "fov_x", "near_clip", "far_clip"]
    assert record["camera_to_world"] == np.round(cam.camera_to_world, 6).tolist()
    back = motion.camera_from_record(json.loads(json.dumps(record)))
    np.testing.assert_allclose(back.camera_to_world, cam.camera_to_world, atol=1e-6)
    assert (back.fov_x, back.near, back.far) == (cam.fov_x, cam.near, cam.far)
    del record["fov_x"]
    with pytest.raises(StoreError, match=r"^x/frame.json: no camera: key 'fov_x' missing") as err:
        motion.camera_from_record(record, "x/frame.json")
    assert "\n" not in str(err.value)


def test_image_without_camera_says_so(tmp_path):
    black = np.zeros((4, 4, 3), np.float32)
    write_image(tmp_path / "old.exr", {"color": black, "color.variance": black})
    assert scan_exr(tmp_path / "old.exr")["matrices"] == {}
    with pytest.raises(StoreError, match="no camera: header attribute 'worldToCamera' and 'worldToNDC' missing"):
        read_camera(tmp_path / "old.exr")


def test_bad_camera_attributes_are_refused(tmp_path):
    import OpenEXR
    chans = {"R": np.zeros((4, 4), np.float32), "G": np.zeros((4, 4), np.float32), "B": np.zeros((4, 4), np.float32)}
    bad = np.eye(4, dtype=np.float32)
    bad[0, 0] = np.inf
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "worldToCamera": bad}, chans) as f:
        f.write(str(tmp_path / "inf.exr"))
    with pytest.raises(StoreError, match="'worldToCamera' has values that are not finite"):
        scan_exr(tmp_path / "inf.exr")
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "worldToNDC": np.eye(3, dtype=np.float32)}, chans) as f:
        f.write(str(tmp_path / "m33.exr"))
    with pytest.raises(StoreError, match="'worldToNDC' is 'm33f' of 36 bytes, expected 'm44f'"):
        scan_exr(tmp_path / "m33.exr")
    # A non-rigid worldToCamera: one line naming the file.
    m = motion.exr_matrices(camera())
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "worldToCamera": 2 * m["worldToCamera"],
                       "worldToNDC": m["worldToNDC"]}, chans) as f:
        f.write(str(tmp_path / "scaled.exr"))
    with pytest.raises(StoreError, match=r"scaled.exr: worldToCamera is not a rigid transform"):
        read_camera(tmp_path / "scaled.exr")


# ---- real renders -------------------------------------------------------------------------------

def test_warped_previous_frame_matches_on_the_tiny_store(tiny_store):
    """GT1 of frame 0 warped into frame 1 (depth and normal tests on) matches frame 1's GT1 on the
    valid pixels far better than frame 0 unwarped: on the tiny store (3 scenes, 32x24, the camera
    moves by a quarter of its distance between the two frames) 30.3, 40.9 and 33.4 dB warped against
    18.9, 27.3 and 22.6 dB unwarped, 52-70 % of the pixels valid (measured; the bound leaves a margin)."""
    from mcdenoise.pipeline import metrics
    from mcdenoise.pipeline.store import Store
    store = Store(tiny_store[0])
    for scene in store.scenes():
        cams = [store.camera(scene, f) for f in (0, 1)]
        prev, cur = (store.read_image(scene, f, "gt1", ["color", "depth", "normal"])[0] for f in (0, 1))
        xy, valid = reproject(cur["depth"], cams[1], cams[0], depth_prev=prev["depth"], normal_t=cur["normal"],
                              normal_prev=prev["normal"])
        assert valid.mean() > 0.3, (scene, valid.mean())
        warped = warp(prev["color"], xy, valid)
        psnr_warped = metrics.psnr(warped[valid], cur["color"][valid])
        psnr_still = metrics.psnr(prev["color"][valid], cur["color"][valid])
        print(f"{scene}: valid {valid.mean():.2f}, warped {psnr_warped:.1f} dB, unwarped {psnr_still:.1f} dB")
        assert psnr_warped > psnr_still + 6, (scene, psnr_warped, psnr_still)
