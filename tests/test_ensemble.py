"""The dihedral self-ensemble (train/infer.py) and its evaluator rows (``<method>_xN``)."""
import numpy as np
import pytest

from mcdenoise.evaluate.methods import parse
from mcdenoise.pipeline.config import ConfigError
from mcdenoise.train import infer


def test_every_transform_is_undone_and_the_eight_are_distinct():
    x = np.random.default_rng(0).random((5, 7, 3), np.float32)
    seen = set()
    for t in infer.TRANSFORMS:
        y = infer.apply_transform(x, t)
        assert y.shape == ((7, 5, 3) if t[0] else (5, 7, 3))
        np.testing.assert_array_equal(infer.invert_transform(y, t), x)
        seen.add(np.ascontiguousarray(y).tobytes())
    assert len(seen) == 8


def test_an_equivariant_denoiser_is_unchanged_and_a_position_bias_is_averaged_away():
    color = np.random.default_rng(1).random((4, 6, 3), np.float32)
    buffers = {"color": color, "albedo": np.ones_like(color)}
    squared = infer.self_ensemble(lambda b: b["color"] ** 2 * b["albedo"], buffers, 8)
    np.testing.assert_allclose(squared, color ** 2, rtol=1e-6)

    def biased(b):   # adds 1 to the first column of whatever copy it is given
        out = b["color"].copy()
        out[:, 0] += 1.0
        return out
    two = infer.self_ensemble(biased, buffers, 2)   # the identity and the horizontal flip
    expected = color.copy()
    expected[:, 0] += 0.5
    expected[:, -1] += 0.5
    np.testing.assert_allclose(two, expected, rtol=1e-6)
    # All eight: the bias lands twice on each border column and, through the transposes, twice on each
    # border row; a quarter of it on each border, half in the corners.
    expected = color.copy()
    expected[:, 0] += 0.25
    expected[:, -1] += 0.25
    expected[0] += 0.25
    expected[-1] += 0.25
    np.testing.assert_allclose(infer.self_ensemble(biased, buffers, 8), expected, rtol=1e-6)
    with pytest.raises(ValueError, match="self-ensemble of 3"):
        infer.self_ensemble(biased, buffers, 3)


def test_method_names_take_the_ensemble_last():
    assert parse("oidn_x8").ensemble == 8 and parse("ours_s3_k4_x4").ensemble == 4 and parse("ours").ensemble == 1
    for bad in ("ours_x8_s3", "oidn_x3", "oidn_s3", "isik_x16"):
        with pytest.raises(ConfigError, match="eval.methods"):
            parse(bad)


def test_the_evaluator_runs_a_self_ensemble_row():
    from mcdenoise.evaluate.methods import Loader, SelfEnsemble
    from mcdenoise.evaluate.stability import synthetic_buffers
    from mcdenoise.pipeline.config import load_config

    loader = Loader(load_config(None, ["eval.device=cpu"]))
    x2, plain = loader.load("oidn_x2", 4), loader.load("oidn", 4)
    assert isinstance(x2, SelfEnsemble) and x2.name == "oidn_x2" and x2.n == 2
    noisy = synthetic_buffers(24, 40, seed=3, noise=0.7)
    out, ref = x2.denoise(noisy), plain.denoise(noisy)
    flipped = plain.denoise({k: np.ascontiguousarray(v[:, ::-1]) for k, v in noisy.items()})[:, ::-1]
    np.testing.assert_allclose(out, (ref + flipped) / 2, rtol=1e-5, atol=1e-7)
