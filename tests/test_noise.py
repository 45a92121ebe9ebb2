"""train/infer.py: telling pixel-independent noise (box filter) from spatially correlated noise
(a wide reconstruction filter, which OIDN does not remove)."""
import numpy as np
import pytest

from mcdenoise.train.infer import CORRELATED_BELOW, correlated_noise, neighbour_ratio
from tests.helpers import cornell_box


def _ramp_with_noise(seed: int, blur: bool) -> np.ndarray:
    rng = np.random.default_rng(seed)
    h, w = 96, 128
    ramp = np.linspace(0.1, 2.0, w)[None, :, None] * np.ones((h, 1, 3))
    noise = rng.standard_normal((h + 2, w + 2, 1))
    if blur:   # each sample splatted over its 3x3 neighbours with Gaussian-like weights
        k = np.array([0.25, 0.5, 0.25])
        noise = sum(k[i] * k[j] * noise[i:i + h, j:j + w] for i in range(3) for j in range(3)) * 2.0
    else:
        noise = noise[1:-1, 1:-1]
    return np.maximum(ramp * (1 + 0.5 * noise), 0).astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_independent_noise_reads_near_one_and_correlated_noise_below_the_threshold(seed):
    independent = neighbour_ratio(_ramp_with_noise(seed, blur=False))
    correlated = neighbour_ratio(_ramp_with_noise(seed, blur=True))
    assert independent > 0.9 and correlated_noise(_ramp_with_noise(seed, blur=False)) is None
    assert correlated < CORRELATED_BELOW and correlated_noise(_ramp_with_noise(seed, blur=True)) == correlated


def test_a_linear_image_without_noise_and_tiny_or_flat_images_say_nothing():
    assert neighbour_ratio(np.full((32, 32, 3), 0.5, np.float32)) is None
    assert neighbour_ratio(np.ones((4, 40, 3), np.float32)) is None


@pytest.mark.parametrize("rfilter,correlated", [("box", False), ("gaussian", True), ("tent", True)])
def test_mitsuba_renders_with_a_wide_filter_are_told_apart(rfilter, correlated):
    img = cornell_box(rfilter)
    assert (correlated_noise(img) is not None) == correlated, neighbour_ratio(img)
