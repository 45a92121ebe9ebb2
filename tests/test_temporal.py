"""The temporal filter and the instability metric (``pipeline.temporal``)."""
import numpy as np
import pytest

from mcdenoise.pipeline import motion
from mcdenoise.pipeline.metrics import reinhard
from mcdenoise.pipeline.motion import Camera
from mcdenoise.pipeline.schema import RADIANCE_COMPONENTS, beauty_from_components
from mcdenoise.pipeline.temporal import (
    AVERAGED,
    InputWindow,
    average_input,
    averaging_kind,
    blend_history,
    blend_sides,
    filtered,
    instability,
    neighbourhood_range,
)


def test_neighbourhood_range_is_the_3x3_min_and_max():
    img = np.random.default_rng(0).uniform(size=(7, 9, 3)).astype(np.float32)
    lo, hi = neighbourhood_range(img)
    for y in range(7):
        for x in range(9):
            win = img[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2].reshape(-1, 3)
            assert np.array_equal(lo[y, x], win.min(0)) and np.array_equal(hi[y, x], win.max(0))


def test_first_frame_and_invalid_pixels_keep_the_current_output():
    rng = np.random.default_rng(1)
    cur = rng.uniform(size=(8, 8, 3)).astype(np.float32)
    assert np.array_equal(blend_history(cur, None, None, 0.3), cur)
    hist = rng.uniform(size=(8, 8, 3)).astype(np.float32)
    valid = np.zeros((8, 8), bool)
    assert np.array_equal(blend_history(cur, hist, valid, 0.3), cur)
    valid[2:5, 3:6] = True
    out = blend_history(cur, hist, valid, 0.3, clamp=False)
    assert np.array_equal(out[~valid], cur[~valid])
    # float32 arithmetic of one multiply-add: within a few ulps of values below 1
    np.testing.assert_allclose(out[valid], 0.3 * cur[valid] + 0.7 * hist[valid], rtol=0, atol=1e-6)
    assert np.array_equal(blend_history(cur, hist, np.ones((8, 8), bool), 1.0), cur)


def test_the_clamp_bounds_a_wrong_history_by_the_current_neighbourhood():
    cur = np.full((6, 6, 3), 0.5, np.float32)
    cur[3, 3] = 2.0
    hist = np.full((6, 6, 3), 1e6, np.float32)                      # a history that is wrong everywhere
    out = blend_history(cur, hist, np.ones((6, 6), bool), 0.5)
    lo, hi = neighbourhood_range(cur)
    assert np.all(out <= hi) and np.all(out >= lo)
    assert out[0, 0, 0] == 0.5 and out[2, 2, 0] == pytest.approx(0.5 * 0.5 + 0.5 * 2.0)


@pytest.mark.parametrize("weight", [0.0, -0.1, 1.5])
def test_a_weight_outside_0_1_is_refused(weight):
    with pytest.raises(ValueError, match="blend weight"):
        blend_history(np.zeros((2, 2, 3)), None, None, weight)


def test_the_unclamped_filter_on_a_still_frame_keeps_w_over_2_minus_w_of_the_noise_variance():
    """An exponential average with weight w of i.i.d. noise has, in steady state, variance
    w / (2 − w) of one frame's: 1/3 at w = 0.5."""
    rng = np.random.default_rng(2)
    truth, w = np.full((256, 256, 3), 1.0, np.float32), 0.5
    hist = None
    for _ in range(40):                                  # (1 − w)^80: the start is forgotten
        frame = truth + rng.normal(0, 0.1, truth.shape).astype(np.float32)
        hist = blend_history(frame, hist, np.ones(truth.shape[:2], bool), w, clamp=False)
    ratio = float(np.var(hist - truth)) / 0.01
    # 196,608 samples: the variance estimate's relative standard error is sqrt(2/N) = 0.3 %
    assert ratio == pytest.approx(w / (2 - w), rel=0.03)


def test_two_sides_are_each_clamped_then_averaged_where_both_are_valid():
    cur = np.zeros((4, 6, 3), np.float32)
    cur[:, 3:] = 1.0                                     # an edge: the 3x3 range is [0, 1] beside it, a point elsewhere
    before, after = np.full_like(cur, 0.8), np.full_like(cur, 0.2)
    v_before, v_after = np.ones((4, 6), bool), np.ones((4, 6), bool)
    v_before[:, 0], v_after[:, 5] = False, False
    out = blend_sides(cur, [(before, v_before), (after, v_after)], 0.5)
    # both valid at the edge (columns 2, 3): the mean of the two histories, 0.5, blended with the frame
    np.testing.assert_allclose(out[:, 2], 0.5 * 0.0 + 0.5 * 0.5, rtol=0, atol=1e-7)
    np.testing.assert_allclose(out[:, 3], 0.5 * 1.0 + 0.5 * 0.5, rtol=0, atol=1e-7)
    # away from the edge each history is clamped to the frame's value: the output is the frame's
    assert np.array_equal(out[:, 1], cur[:, 1]) and np.array_equal(out[:, 4], cur[:, 4])
    # one side valid: that side alone, as blend_history has it
    one = blend_sides(cur, [(before, v_before), (after, ~v_after)], 0.5)
    np.testing.assert_array_equal(one, blend_history(cur, before, v_before, 0.5))
    assert np.array_equal(blend_sides(cur, [(before, ~v_before & False), (after, v_after & False)], 0.5), cur)


def _ramp_sequence(offsets, h=6, w=12):
    """Frames of a still camera: a ramp of slope 1 a pixel (its 3x3 range is +-1 around each inner pixel, so a
    history within 1 is never clamped there) plus a constant offset per frame."""
    view = motion.View(Camera(np.eye(4), 50.0, w, h), np.full((h, w), 3.0))
    ramp = np.broadcast_to(np.arange(w, dtype=np.float32)[None, :, None], (h, w, 3))
    return [(ramp + np.float32(e), view) for e in offsets], ramp


def test_the_filter_along_a_still_sequence_is_the_exponential_average_causal_or_on_both_sides():
    offsets, w = [0.3, -0.2, 0.1, 0.4, -0.3], 0.6
    frames, ramp = _ramp_sequence(offsets)
    inner = (slice(1, -1), slice(1, -1))
    causal = [y for y, _ in filtered(frames, w)]
    f = [offsets[0]]
    for e in offsets[1:]:
        f.append(w * e + (1 - w) * f[-1])
    both = list(filtered(frames, w, ahead=2))
    for t in range(len(offsets)):
        np.testing.assert_allclose(causal[t][inner] - ramp[inner], f[t], rtol=0, atol=1e-5)
        # the backward filter from frame t + 2, then frame t's history the mean of both sides' (where there are two)
        later = offsets[t + 1:t + 3]
        sides = [f[t - 1]] if t > 0 else []
        if later:
            b = later[-1]
            for e in later[-2::-1]:
                b = w * e + (1 - w) * b
            sides.append(b)
        expected = w * offsets[t] + (1 - w) * np.mean(sides)
        np.testing.assert_allclose(both[t][0][inner] - ramp[inner], expected, rtol=0, atol=1e-5)
        assert both[t][1].all()                                          # every pixel had a history
    assert causal[0] is not None and np.array_equal(causal[0], frames[0][0])
    # the backward filter from one frame after: frame t + 1's output alone is the history of that side
    near = list(filtered(frames, w, ahead=4, reach=1))
    for t in range(len(offsets) - 1):
        sides = ([f[t - 1]] if t > 0 else []) + [offsets[t + 1]]
        np.testing.assert_allclose(near[t][0][inner] - ramp[inner], w * offsets[t] + (1 - w) * np.mean(sides),
                                   rtol=0, atol=1e-5)


def test_the_filter_yields_a_failed_frame_as_none_and_restarts_after_it():
    frames, _ = _ramp_sequence([0.1, 0.2, 0.3, 0.4])
    frames[1] = (None, frames[1][1])
    out = list(filtered(frames, 0.5, ahead=1))
    assert out[1] == (None, None)
    # frame 0 has no usable frame after it, frame 2 none before it: each is what the frame after alone gives
    assert np.array_equal(out[0][0], frames[0][0]) and out[0][1] is None
    alone = list(filtered(frames[2:], 0.5, ahead=1))
    np.testing.assert_array_equal(out[2][0], alone[0][0])
    np.testing.assert_array_equal(out[3][0], alone[1][0])


def test_instability_is_zero_for_the_reference_and_for_an_error_that_stays():
    rng = np.random.default_rng(3)
    ref = rng.uniform(0, 4, (16, 16, 3))
    ref_prev = ref * rng.uniform(0.9, 1.1, ref.shape)                 # the scene changes a little
    valid = np.ones((16, 16), bool)
    assert instability(ref, ref_prev, ref, ref_prev, valid) == 0.0
    biased = ref + 0.3                                                # a still frame with a fixed error
    assert instability(biased, biased, ref, ref, valid) == 0.0


def test_instability_of_fresh_noise_and_the_mask():
    rng = np.random.default_rng(4)
    ref = rng.uniform(0, 1, (32, 32, 3))
    a, b = ref + rng.normal(0, 0.05, ref.shape), ref + rng.normal(0, 0.05, ref.shape)
    valid = rng.uniform(size=(32, 32)) < 0.7
    expected = np.abs(reinhard(a) - reinhard(b))[valid].mean()
    assert instability(a, b, ref, ref, valid) == pytest.approx(expected, rel=1e-12)
    a_bad = a.copy()
    a_bad[~valid] = 1e9                                               # invalid pixels do not count
    assert instability(a_bad, b, ref, ref, valid) == pytest.approx(expected, rel=1e-12)
    assert np.isnan(instability(a, b, ref, ref, np.zeros((32, 32), bool)))


# ---- the input averaged over the previous frames ------------------------------------------------

def frame_buffers(rng, h=6, w=8) -> dict[str, np.ndarray]:
    """Noisy radiance components (and their variances), the beauty their sum, an albedo."""
    out = {n: rng.uniform(0, 2, (h, w, 3)).astype(np.float32) for n in RADIANCE_COMPONENTS}
    out["color"] = beauty_from_components(out)
    for n in ("color", *RADIANCE_COMPONENTS):
        out[f"{n}.variance"] = rng.uniform(0, 0.5, (h, w, 3)).astype(np.float32)
    out["albedo"] = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    return out


def still(h=6, w=8, shift=0.0, valid=None):
    """motion.trace's answer for a past frame seen ``shift`` pixels to the left of frame t."""
    xy = motion.pixel_centres(w, h) - [shift, 0]
    return xy.astype(np.float32), np.ones((h, w), bool) if valid is None else valid


def test_colour_average_is_the_mean_of_the_frames_and_divides_their_variance():
    rng = np.random.default_rng(0)
    frames = [frame_buffers(rng) for _ in range(3)]
    mask = np.ones((6, 8), bool)
    mask[2, 3] = False                                       # frame t-2 does not see this pixel
    out, count = average_input(frames[0], frames[1:], [still(), still(valid=mask)], "colour")
    for n in ("color", *RADIANCE_COMPONENTS):
        mean = np.mean([f[n].astype(np.float64) for f in frames], axis=0)
        np.testing.assert_allclose(out[n][mask], mean[mask], rtol=1e-6)
        var = np.sum([f[f"{n}.variance"].astype(np.float64) for f in frames], axis=0) / 9
        np.testing.assert_allclose(out[f"{n}.variance"][mask], var[mask], rtol=1e-6)
    two = (frames[0]["color"][2, 3].astype(np.float64) + frames[1]["color"][2, 3]) / 2
    np.testing.assert_allclose(out["color"][2, 3], two, rtol=1e-6)
    assert count[2, 3] == 2 and (count[mask] == 3).all()
    np.testing.assert_array_equal(out["albedo"], frames[0]["albedo"])        # not radiance: frame t's
    # the beauty stays the sum of the components (each averaged the same way)
    np.testing.assert_allclose(out["color"], beauty_from_components(out), rtol=1e-5, atol=1e-6)


def test_diffuse_average_keeps_this_frames_reflections_and_emission():
    rng = np.random.default_rng(1)
    frames = [frame_buffers(rng) for _ in range(2)]
    out, _ = average_input(frames[0], frames[1:], [still()], "diffuse")
    for n in ("emission", "specular_direct", "specular_indirect"):
        np.testing.assert_array_equal(out[n], frames[0][n])
    for n in ("diffuse_direct", "diffuse_indirect"):
        np.testing.assert_allclose(out[n], (frames[0][n].astype(np.float64) + frames[1][n]) / 2, rtol=1e-6)
        np.testing.assert_allclose(out[f"{n}.variance"],
                                   (frames[0][f"{n}.variance"].astype(np.float64) + frames[1][f"{n}.variance"]) / 4,
                                   rtol=1e-6)
    np.testing.assert_allclose(out["color"], beauty_from_components(out), rtol=1e-6)
    # the beauty's variance: frame t's, its diffuse share replaced by the averaged one
    share = sum(out[f"{n}.variance"].astype(np.float64) - frames[0][f"{n}.variance"]
                for n in ("diffuse_direct", "diffuse_indirect"))
    np.testing.assert_allclose(out["color.variance"], np.maximum(frames[0]["color.variance"] + share, 0),
                               rtol=1e-5, atol=1e-7)
    # a frame without components (a user's beauty only) is left alone
    bare = [{"color": f["color"]} for f in frames]
    out, count = average_input(bare[0], bare[1:], [still()], "diffuse")
    np.testing.assert_array_equal(out["color"], bare[0]["color"])
    assert (count == 1).all()


def test_past_frames_are_read_whole_at_the_pixel_the_spot_falls_in():
    """A past frame seen 1.3 pixels to the left: each pixel takes the past pixel 1.3 to its left falls in,
    unmixed with its neighbours (the noise stays white)."""
    rng = np.random.default_rng(2)
    frames = [frame_buffers(rng) for _ in range(2)]
    valid = np.ones((6, 8), bool)
    valid[:, :2] = False                                     # off the left edge of the past frame
    out, _ = average_input(frames[0], frames[1:], [still(shift=1.3, valid=valid)], "colour")
    past = np.zeros_like(frames[1]["color"])
    # column i's centre i + 0.5 lands at i - 0.8, in past column i - 1
    past[:, 2:] = frames[1]["color"][:, np.floor(np.arange(2, 8) + 0.5 - 1.3).astype(int)]
    expected = np.where(valid[..., None], (frames[0]["color"].astype(np.float64) + past) / 2, frames[0]["color"])
    np.testing.assert_allclose(out["color"], expected, rtol=1e-6)


def test_the_window_keeps_its_last_frames_and_stops_at_a_frame_without_motion():
    rng = np.random.default_rng(3)
    cam = Camera(np.eye(4), 50.0, 8, 6)
    view = motion.View(cam, np.full((6, 8), 3.0))
    frames = [frame_buffers(rng) for _ in range(5)]
    window = InputWindow(3, "colour")
    np.testing.assert_array_equal(window.take(frames[0], view)["color"], frames[0]["color"])
    window.take(frames[1], view)
    out = window.take(frames[2], view)                       # frames 0, 1, 2: the window is full
    np.testing.assert_allclose(out["color"], np.mean([f["color"].astype(np.float64) for f in frames[:3]], 0),
                               rtol=1e-6)
    out = window.take(frames[3], view)                       # frames 1, 2, 3: frame 0 has left
    np.testing.assert_allclose(out["color"], np.mean([f["color"].astype(np.float64) for f in frames[1:4]], 0),
                               rtol=1e-6)
    assert window.counts == [2.0, 3.0, 3.0] and len(window.past) == 2
    window.take(frames[4], None)                             # no motion: alone, and it cuts the window
    np.testing.assert_array_equal(window.take(frames[0], view)["color"], frames[0]["color"])
    assert InputWindow(1).take(frames[0], view) is frames[0]
    with pytest.raises(ValueError, match="must be >= 1"):
        InputWindow(0)


def test_the_window_averages_the_frames_ahead_it_is_given_that_are_linked_to_it():
    rng = np.random.default_rng(10)
    cam = Camera(np.eye(4), 50.0, 8, 6)
    view = motion.View(cam, np.full((6, 8), 3.0))
    frames = [frame_buffers(rng) for _ in range(5)]
    window = InputWindow(2, "colour", ahead=2)
    mean = lambda fs: np.mean([f["color"].astype(np.float64) for f in fs], 0)  # noqa: E731
    ahead = [(window.keep(f), view) for f in frames[1:4]]         # three given, two used
    np.testing.assert_allclose(window.take(frames[0], view, ahead)["color"], mean(frames[:3]), rtol=1e-6)
    # frame 1: frame 0 behind it, frames 2 and 3 ahead
    out = window.take(frames[1], view, [(window.keep(f), view) for f in frames[2:4]])
    np.testing.assert_allclose(out["color"], mean(frames[:4]), rtol=1e-6)
    # a frame ahead that shares no motion with this one (vectors there, a camera here) does not count, nor those
    # after it
    vectors = motion.View(None, None, motion=np.zeros((6, 8, 4), np.float32))
    out = window.take(frames[2], view, [(window.keep(frames[3]), vectors), (window.keep(frames[4]), view)])
    np.testing.assert_allclose(out["color"], mean(frames[1:3]), rtol=1e-6)
    assert window.counts == [3.0, 4.0, 2.0]
    # with motion vectors here and there the frames ahead count, followed forward along the vectors
    forward = InputWindow(1, "colour", ahead=2)
    out = forward.take(frames[0], vectors, [(forward.keep(f), vectors) for f in frames[1:4]])
    np.testing.assert_allclose(out["color"], mean(frames[:3]), rtol=1e-6)
    # nothing behind and nothing ahead: the frame's own buffers
    assert InputWindow(1, ahead=2).take(frames[0], view) is frames[0]
    with pytest.raises(ValueError, match="ahead: must be >= 0"):
        InputWindow(2, ahead=-1)


def test_the_gate_keeps_a_past_frame_only_where_it_agrees_within_noise():
    """Frame t-1's diffuse light is frame t's plus 1.5 standard deviations of the difference on the left half and
    plus 4 on the right half: a gate of 3 keeps the left half and rejects the right, no gate keeps both."""
    rng = np.random.default_rng(4)
    now = frame_buffers(rng)
    past = {k: v.copy() for k, v in now.items()}
    spread = np.sqrt(sum(now[f"{n}.variance"].astype(np.float64) + past[f"{n}.variance"]
                         for n in ("diffuse_direct", "diffuse_indirect")))
    shift = np.where(np.arange(8)[None, :, None] < 4, 1.5, 4.0) * spread
    past["diffuse_direct"] = (now["diffuse_direct"] + shift).astype(np.float32)
    _, count = average_input(now, [past], [still()], "diffuse", gate=3.0)
    np.testing.assert_array_equal(count, np.where(np.arange(8)[None, :] < 4, 2, 1) * np.ones((6, 1)))
    _, count = average_input(now, [past], [still()], "diffuse")
    assert (count == 2).all()
    out, _ = average_input(now, [past], [still()], "diffuse", gate=3.0)
    np.testing.assert_array_equal(out["diffuse_direct"][:, 4:], now["diffuse_direct"][:, 4:])


def test_irradiance_average_keeps_this_frames_texture_and_averages_the_light_under_it():
    """Each frame's diffuse light is its albedo times a noisy irradiance; frame t-1 sees another albedo (a texture
    half a pixel off). ``irradiance`` gives frame t's albedo times the mean irradiance, its variance frame t's
    albedo squared times the mean of the irradiance variances over 2 squared; where a channel's albedo is black in
    one frame only, the past pixel does not count."""
    rng = np.random.default_rng(7)
    frames = [frame_buffers(rng) for _ in range(2)]
    for f in frames:
        f["albedo"] = rng.uniform(0.1, 0.9, (6, 8, 3)).astype(np.float32)
    frames[1]["albedo"][1, 2, 0] = 0.0                       # black in frame t-1 only: another surface there
    frames[0]["albedo"][4, 5, 1] = frames[1]["albedo"][4, 5, 1] = 0.0   # black in both: averaged as it is
    out, count = average_input(frames[0], frames[1:], [still()], "irradiance")
    assert count[1, 2] == 1 and (np.delete(count.ravel(), 1 * 8 + 2) == 2).all()
    a = [np.where(f["albedo"] > 1e-3, f["albedo"].astype(np.float64), 1.0) for f in frames]
    for n in ("diffuse_direct", "diffuse_indirect"):
        light = a[0] * (frames[0][n] / a[0] + frames[1][n] / a[1]) / 2
        light[1, 2] = frames[0][n][1, 2]
        np.testing.assert_allclose(out[n], light, rtol=1e-5)
        v = [f[f"{n}.variance"] / (ai * ai) for f, ai in zip(frames, a)]
        var = a[0] ** 2 * (v[0] + v[1]) / 4
        var[1, 2] = frames[0][f"{n}.variance"][1, 2]
        np.testing.assert_allclose(out[f"{n}.variance"], var, rtol=1e-5)
    for n in ("emission", "specular_direct", "specular_indirect", "albedo"):
        np.testing.assert_array_equal(out[n], frames[0][n])
    np.testing.assert_allclose(out["color"], beauty_from_components(out), rtol=1e-5)


def test_an_albedo_at_the_floor_is_lit_alike_in_every_frame():
    """A float32 albedo of exactly float32(ALBEDO_FLOOR) lies above the float64 floor: frame t's and the past
    frame's are compared with the floor alike (in float64), so the same surface in both counts twice."""
    rng = np.random.default_rng(8)
    frames = [frame_buffers(rng) for _ in range(2)]
    for f in frames:
        f["albedo"][:, :, 0] = np.float32(1e-3)
    _, count = average_input(frames[0], frames[1:], [still()], "irradiance")
    assert (count == 2).all()


def test_irradiance_gate_passes_a_texture_the_diffuse_gate_refuses():
    """The same irradiance under another albedo in frame t-1 (no noise between them): the diffuse light differs by
    far more than its standard deviation, so ``diffuse`` gated at 2 refuses every past pixel, while ``irradiance``
    counts them all and gives frame t's light back exactly."""
    rng = np.random.default_rng(8)
    now = frame_buffers(rng)
    irradiance = {n: rng.uniform(0.5, 2, (6, 8, 3)) for n in ("diffuse_direct", "diffuse_indirect")}
    past = {k: v.copy() for k, v in now.items()}
    now["albedo"], past["albedo"] = (np.full((6, 8, 3), 0.2, np.float32), np.full((6, 8, 3), 0.8, np.float32))
    for f in (now, past):
        for n, e in irradiance.items():
            f[n] = (f["albedo"] * e).astype(np.float32)
            f[f"{n}.variance"] = np.full((6, 8, 3), 1e-4, np.float32)
    _, count = average_input(now, [past], [still()], "diffuse", gate=2.0)
    assert (count == 1).all()
    out, count = average_input(now, [past], [still()], "irradiance", gate=2.0)
    assert (count == 2).all()
    for n in irradiance:
        np.testing.assert_allclose(out[n], now[n], rtol=1e-5)
        # each frame's variance divided by its albedo squared, averaged over 2 frames, times frame t's albedo squared
        np.testing.assert_allclose(out[f"{n}.variance"], 0.2 ** 2 * (1e-4 / 0.04 + 1e-4 / 0.64) / 4, rtol=1e-5)


def test_input_window_keeps_the_albedo_it_demodulates_by():
    rng = np.random.default_rng(9)
    frames = [frame_buffers(rng) for _ in range(3)]
    view = motion.View(Camera(np.eye(4), 60.0, 8, 6), np.full((6, 8), 2.0, np.float32), None)
    window = InputWindow(3, "irradiance")
    for f in frames[:2]:
        window.take(f, view)
    assert all("albedo" in past for past, _ in window.past)
    out = window.take(frames[2], view)
    expected, _ = average_input(frames[2], frames[1::-1], motion.trace(view, [view, view]), "irradiance")
    for n in ("diffuse_direct", "diffuse_direct.variance", "color"):
        np.testing.assert_allclose(out[n], expected[n], rtol=1e-6)


def test_components_gate_each_reflection_apart_from_the_diffuse_light():
    """A reflection that moved (frame t-1's specular_direct far off frame t's on the right half): with
    ``components`` the diffuse light and specular_indirect average everywhere, specular_direct only on the left
    half; the beauty is the sum of the averaged components and frame t's emission, its variance frame t's with
    every averaged component's share replaced."""
    rng = np.random.default_rng(5)
    now = frame_buffers(rng)
    past = frame_buffers(rng)
    for n in RADIANCE_COMPONENTS:                  # within noise of frame t everywhere ...
        past[n] = now[n].copy()
    right = np.arange(8)[None, :, None] >= 4       # ... but the reflection moved on the right half
    past["specular_direct"] = np.where(right, now["specular_direct"] + 100, now["specular_direct"]).astype(np.float32)
    out, count = average_input(now, [past], [still()], "components", gate=2.0)
    assert (count == 2).all()                      # the first group's count: the diffuse light
    for n in ("diffuse_direct", "diffuse_indirect", "specular_indirect"):
        np.testing.assert_allclose(out[f"{n}.variance"], (now[f"{n}.variance"].astype(np.float64)
                                                          + past[f"{n}.variance"]) / 4, rtol=1e-6)
    spec = np.where(right, now["specular_direct"], (now["specular_direct"].astype(np.float64) + past["specular_direct"]) / 2)
    np.testing.assert_allclose(out["specular_direct"], spec, rtol=1e-6)
    var = np.where(right, now["specular_direct.variance"],
                   (now["specular_direct.variance"].astype(np.float64) + past["specular_direct.variance"]) / 4)
    np.testing.assert_allclose(out["specular_direct.variance"], var, rtol=1e-6)
    np.testing.assert_array_equal(out["emission"], now["emission"])
    np.testing.assert_allclose(out["color"], beauty_from_components(out), rtol=1e-6)
    share = sum(out[f"{n}.variance"].astype(np.float64) - now[f"{n}.variance"] for n in AVERAGED["components"])
    np.testing.assert_allclose(out["color.variance"], np.maximum(now["color.variance"] + share, 0), rtol=1e-5, atol=1e-7)
    # diffuse: the reflections are frame t's whatever the gate
    out, _ = average_input(now, [past], [still()], "diffuse", gate=2.0)
    np.testing.assert_array_equal(out["specular_indirect"], now["specular_indirect"])


def test_frames_without_the_gates_variances_average_the_light_divided_by_the_albedo():
    buffers = frame_buffers(np.random.default_rng(11))
    assert averaging_kind(buffers) == "diffuse"
    bare = {k: v for k, v in buffers.items() if not k.endswith(".variance")}     # a Cycles render's layers
    assert averaging_kind(bare) == "irradiance"
    assert averaging_kind({k: v for k, v in bare.items() if k != "albedo"}) == "diffuse"   # nothing to divide by
