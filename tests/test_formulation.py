"""The formulation (train/sampler.py): the min-SNR weight, the training timesteps, the rules the
config and model.json records share, and records from before the per-crop loss."""
import re

import numpy as np
import pytest
import torch

from mcdenoise.pipeline.config import ConfigError, load_config
from mcdenoise.train.sampler import CONFIG_KEYS, Formulation, FormulationError, snr_weight


@pytest.mark.slow
def test_min_snr_weight_has_a_floor_at_zero_snr_and_gamma_at_low_noise():
    sched = Formulation().scheduler("ddpm")
    t = torch.tensor([0, 500, 999])
    w0 = snr_weight(sched, t, gamma=5.0, floor=1.0)
    assert w0[2] == pytest.approx(1.0) and w0[0] == pytest.approx(5.0)
    assert torch.all(snr_weight(sched, t, 5.0, 0.0)[:2] > 0)
    assert snr_weight(sched, t, 5.0, 0.0)[2] == 0      # the trap the floor avoids


def test_training_timesteps_focus_on_the_samplers_steps():
    f = Formulation(t_focus=1.0)
    focus = f.train_timesteps([1, 3])
    assert [x.tolist() for x in focus] == [[999], [999, 666, 332]]
    t = f.draw_t(6000, focus, torch.Generator().manual_seed(0)).numpy()
    assert set(t.tolist()) <= {332, 666, 999}
    # each step count half the time: 999 in 1/2 + 1/6 of the draws, 666 and 332 in 1/6 each
    assert abs((t == 999).mean() - 2 / 3) < 0.03 and abs((t == 332).mean() - 1 / 6) < 0.03
    mixed = Formulation(t_focus=0.5).draw_t(4000, focus, torch.Generator().manual_seed(0))
    share = np.isin(mixed.numpy(), [332, 666, 999]).mean()
    assert 0.45 < share < 0.56


def test_the_defaults_are_the_shipped_models():
    """A new run's formulation (the config's defaults) is the one train/shipped records."""
    import json

    from mcdenoise.train.model import SHIPPED_MODEL
    shipped = json.loads((SHIPPED_MODEL / "model.json").read_text())
    assert Formulation.from_config(load_config(None, []).diffusion).record() == shipped["formulation"]


@pytest.mark.parametrize("bad,match", [
    (dict(loss_norm="pixel"), "diffusion.loss_norm"),
    (dict(prediction="epsilon"), "diffusion.prediction"),
    (dict(estimate="none"), "diffusion.estimate"),
    (dict(residual=False), "diffusion.residual"),
    (dict(sampler="ddpm"), "diffusion.sampler"),
    (dict(start="middle"), "diffusion.start"),
    (dict(schedule="linear"), "diffusion.schedule"),
    (dict(steps=3, skip=3), "diffusion.skip"),
    (dict(start="noise", steps=3, skip=1), "diffusion.skip"),
])
def test_formulation_refuses_what_cannot_work(bad, match):
    with pytest.raises(FormulationError, match=match):
        Formulation(**bad)


def test_steps_and_skips():
    assert Formulation(steps=50, skip=30).skip == 30
    with pytest.raises(FormulationError, match=r"^diffusion\.skip: need 0 <= skip < steps \(50\), got 50$"):
        Formulation(steps=50, skip=50)
    with pytest.raises(FormulationError, match=r"^diffusion\.steps: need 1 <= steps <= 1000, got 0$"):
        Formulation(steps=0)


def test_a_record_with_a_bad_combination_is_refused():
    """Formulation is also built from model.json records: it checks itself, whatever the source."""
    record = Formulation().record()
    with pytest.raises(FormulationError, match=r"diffusion\.skip"):
        Formulation.from_record({**record, "steps": 3, "skip": 3})
    with pytest.raises(FormulationError, match=r"diffusion\.prediction"):
        Formulation.from_record({**record, "prediction": "epsilon"})
    assert issubclass(FormulationError, ConfigError)


GRID = [dict(schedule=s, start=st, steps=n, skip=k)
        for s in ("if", "zero_snr", "cosine") for st in ("estimate", "noise")
        for n, k in ((1, 0), (50, 30), (50, 50), (0, 0))]


@pytest.mark.parametrize("values", GRID, ids=lambda v: "-".join(str(x) for x in v.values()))
def test_the_config_and_the_formulation_apply_the_same_rules(values):
    """One set of rules (pipeline.config.check_formulation): a diffusion section loads exactly when a
    Formulation of the same fields can be built, and both name the same key."""
    assert set(values) <= set(CONFIG_KEYS)

    def outcome(build):
        try:
            build()
        except ConfigError as exc:
            return re.search(r"diffusion\.\w+", str(exc)).group(0)
        return "ok"
    in_config = outcome(lambda: load_config(None, [f"diffusion.{k}={v}" for k, v in values.items()]))
    assert in_config == outcome(lambda: Formulation(**values))


def test_records_round_trip_and_runs_from_before_loss_norm_keep_their_fingerprint():
    crop = Formulation(loss_norm="crop")
    assert Formulation.from_record(crop.record()) == crop
    # a model.json record as exported before the key existed
    before = {"estimate": "oidn", "prediction": "sample", "residual": True, "residual_scale": 0.05, "sampler": "ddim",
              "schedule": "zero_snr", "skip": 0, "snr_floor": 1.0, "snr_gamma": 5.0, "start": "estimate", "steps": 1,
              "t_focus": 0.8}
    old = Formulation.from_record(before)
    assert old.loss_norm == "none" and old.record() == before
