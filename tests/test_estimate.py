"""First estimates (train/estimate.py): OIDN, the Isik network and their mean, and how they enter the
condition and a trained run's record."""
import numpy as np
import pytest

from mcdenoise.clean.apply import denoise
from mcdenoise.clean.data import IN_CHANNELS, frame_inputs
from mcdenoise.clean.model import AffinityDenoiser
from mcdenoise.pipeline import oidn
from mcdenoise.pipeline.exr import StoreError
from mcdenoise.train.data import AUX_CHANNELS, aux_names, model_inputs, to_planar
from mcdenoise.train.estimate import Estimator, extra_names, load
from tests.helpers import save_untrained_isik


def frame(seed=0, h=20, w=24):
    from mcdenoise.evaluate.stability import synthetic_buffers
    return synthetic_buffers(h, w, seed=seed)


def isik_model():
    return AffinityDenoiser(IN_CHANNELS, embed_channels=8, channels=[8, 8], affinity_channels=4, kernel_size=3,
                            dilations=[1, 2])


def test_mean_of_oidn_and_isik_and_its_components():
    b = frame()
    model = isik_model()
    est, parts = Estimator("oidn+isik", model)(b)
    want_oidn = oidn.denoise(b)
    want_isik = denoise(model, *frame_inputs(b))
    np.testing.assert_array_equal(parts[0], want_oidn)
    np.testing.assert_allclose(parts[1], want_isik, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(est, (want_oidn + want_isik) / 2, rtol=1e-6, atol=1e-7)
    assert Estimator("none")(b) == (None, [])


def test_components_become_condition_channels_only_when_there_are_several():
    b = frame(1)
    assert extra_names("oidn") == [] and aux_names("oidn") == aux_names()
    names = aux_names("oidn+isik")
    assert len(names) == AUX_CHANNELS + 6 and names[-6:] == extra_names("oidn+isik")
    est, parts = Estimator("oidn+isik", isik_model())(b)
    _, aux = model_inputs(b, 4, estimates=parts)
    assert aux.shape[0] == len(names)
    np.testing.assert_array_equal(aux[-3:], to_planar(parts[1]))
    _, aux1 = model_inputs(b, 4, estimates=parts[:1])
    assert aux1.shape[0] == AUX_CHANNELS


def test_an_isik_estimate_needs_a_trained_network(tmp_path):
    with pytest.raises(ValueError, match="needs an Isik model"):
        Estimator("isik")
    with pytest.raises(StoreError, match="make train MODEL=isik SPP=any"):
        load("oidn+isik", tmp_path / "nothing")
    save_untrained_isik(tmp_path / "isik")
    est = load("oidn+isik", tmp_path / "isik")
    assert est.kind == "oidn+isik" and est.isik is not None
    with pytest.raises(StoreError, match="unknown first estimate"):
        load("bm3d", None)


def test_an_input_without_the_renderers_buffers_gets_oidn_for_isik():
    """An EXR from elsewhere (R, G, B, maybe albedo and normal, no variance): the Isik network never saw such
    inputs, so OIDN stands in for it and the mean is OIDN's output."""
    b = frame(2)
    rgb_only = {"color": b["color"]}
    est, parts = Estimator("oidn+isik", isik_model())(rgb_only)
    np.testing.assert_array_equal(est, oidn.denoise(rgb_only))
    assert len(parts) == 2 and np.array_equal(parts[0], parts[1])
    no_variance = {k: v for k, v in b.items() if k != "color.variance"}
    np.testing.assert_array_equal(Estimator("oidn+isik", isik_model())(no_variance)[0], oidn.denoise(no_variance))
