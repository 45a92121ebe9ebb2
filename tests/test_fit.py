"""The shared training loop (clean.fit) on a toy task, and the shared feature table (pipeline.schema)
as the cleaner's and the diffusion model's encoders use it."""
import json

import numpy as np
import pytest
import torch

from mcdenoise.clean.fit import Task, fit
from mcdenoise.pipeline import schema
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.exr import atomic_write_json


class Toy(Task):
    """One weight w fitted to 3 by SGD on (w - 3)^2; validation returns ``scores[epoch]``
    (``epoch`` 0: before the first step). ``nan_from``: steps from this epoch on are non-finite."""

    def __init__(self, folder, epochs, scores, minimize=True, validate_initial=False, nan_from=None, budget=0.0):
        self.name, self.folder, self.epochs, self.fingerprint, self.fmt = "toy", folder, epochs, {"lr": 0.1}, "toy"
        self.state = torch.nn.Linear(1, 1, bias=False)
        torch.nn.init.zeros_(self.state.weight)
        self.optimizers = torch.optim.SGD(self.state.parameters(), lr=0.1)
        self.device, self.minimize, self.validate_initial = torch.device("cpu"), minimize, validate_initial
        self.scores, self.nan_from, self.time_budget_s, self.nan_limit = scores, nan_from, budget, 2
        self.saved, self.epoch = [], 0

    def batches(self, epoch):
        self.epoch = epoch + 1
        return [{"x": torch.ones(1)}] * 2

    def step(self, batch, epoch, index):
        w = self.state.weight.sum()
        loss = (w - 3) ** 2 * (float("nan") if self.nan_from is not None and epoch + 1 >= self.nan_from else 1)
        self.optimizers.zero_grad()
        loss.backward()
        finite = bool(torch.isfinite(loss))
        if finite:
            self.optimizers.step()
        return {"loss": float(loss.detach())}, finite

    def entry(self, epoch, kept, skipped):
        return {"epoch": epoch + 1, "train_loss": float(np.mean([t["loss"] for t in kept])) if kept else None,
                "skipped_steps": skipped}

    def validate(self):
        return {"score": self.scores[self.epoch]}

    def score(self, entry):
        return entry["val"]["score"]

    def save_best(self, entry):
        self.saved.append(entry["epoch"])

    def write_history(self, history, best):
        atomic_write_json(self.folder / "train.json", {"history": history, "best": best})

    def epoch_line(self, entry):
        return f"toy epoch {entry['epoch']}"


def test_best_follows_the_score_direction(tmp_path):
    low = Toy(tmp_path / "low", 3, {1: 0.5, 2: 0.2, 3: 0.4})
    s = fit(low, quiet=True)
    assert low.saved == [1, 2] and s["best"]["epoch"] == 2 and s["epochs"] == 3 and s["trained_epochs"] == 3
    high = Toy(tmp_path / "high", 3, {1: 0.5, 2: 0.2, 3: 0.4}, minimize=False)
    assert fit(high, quiet=True)["best"]["epoch"] == 1 and high.saved == [1]


def test_initial_validation_is_a_candidate(tmp_path):
    toy = Toy(tmp_path, 2, {0: 10.0, 1: 5.0, 2: 20.0}, minimize=False, validate_initial=True)
    s = fit(toy, quiet=True)
    history = json.loads((tmp_path / "train.json").read_text())["history"]
    assert [h["epoch"] for h in history] == [0, 1, 2] and history[0]["train_loss"] is None
    assert toy.saved == [0, 2] and s["best"]["epoch"] == 2


def test_resume_matches_an_uninterrupted_run_and_cleans_stale_files(tmp_path):
    straight = Toy(tmp_path / "a", 3, {1: 3, 2: 2, 3: 1})
    fit(straight, quiet=True)
    fit(Toy(tmp_path / "b", 1, {1: 3}), quiet=True)
    stale = tmp_path / "b" / ".last.safetensors.abc.tmp"
    stale.write_bytes(b"partial")
    resumed = Toy(tmp_path / "b", 3, {1: 3, 2: 2, 3: 1})
    s = fit(resumed, quiet=True)
    assert s["trained_epochs"] == 2 and not stale.exists()
    assert torch.equal(straight.state.weight, resumed.state.weight)
    a, b = (json.loads((tmp_path / d / "train.json").read_text()) for d in ("a", "b"))
    assert [h["train_loss"] for h in a["history"]] == [h["train_loss"] for h in b["history"]]
    again = Toy(tmp_path / "b", 3, {})
    assert fit(again, quiet=True)["trained_epochs"] == 0 and again.saved == []


def test_time_budget_stops_after_an_epoch(tmp_path, capsys):
    s = fit(Toy(tmp_path, 3, {1: 1, 2: 1, 3: 1}, budget=1e-9))
    assert s["epochs"] == 1 and "time budget of 1e-09 s reached after epoch 1; rerun to resume" in capsys.readouterr().out


def test_time_budget_counts_from_the_data_loaded(tmp_path, monkeypatch):
    """Loading the data (``Task.prepare``; a million seconds here) is not training: a budget of a thousand seconds
    still trains every epoch, and the epochs' ``seconds`` start after it."""
    import time
    real_clock, late = time.perf_counter, [0.0]
    monkeypatch.setattr(time, "perf_counter", lambda: real_clock() + late[0])
    task = Toy(tmp_path, 3, {1: 1, 2: 1, 3: 1}, budget=1e3)
    task.prepare = lambda: late.__setitem__(0, late[0] + 1e6)
    s = fit(task, quiet=True)
    history = json.loads((tmp_path / "train.json").read_text())["history"]
    assert s["epochs"] == 3 and s["seconds"] < 1e3 and all(e["seconds"] < 1e3 for e in history)


def test_nan_limit_in_a_row_stops_the_run(tmp_path):
    with pytest.raises(TrainError, match=r"toy: 2 steps in a row had a non-finite loss or gradient \(epoch 2"):
        fit(Toy(tmp_path, 3, {1: 1, 2: 1, 3: 1}, nan_from=2), quiet=True)
    # epoch 1 was committed before the failure, so a rerun resumes from it
    assert json.loads((tmp_path / "train.json").read_text())["best"]["epoch"] == 1


# ---- the feature table ---------------------------------------------------------------------------

def _buffers(rng, size=6):
    out = {}
    for b in schema.BUFFERS:
        scale = 5.0 if b.radiance else 1.0
        x = rng.uniform(-0.2 if b.name == "normal" else 0, scale, (size, size, b.size)).astype(np.float32)
        if b.name == "normal":
            x = x * 1.1 - 0.5     # some values outside [-1, 1]
        out[b.name] = x
        out[schema.variance_name(b.name)] = rng.uniform(0, 0.5, (size, size, b.size)).astype(np.float32)
    return out


def test_a_missing_buffer_is_its_background_before_the_encoding():
    b = _buffers(np.random.default_rng(1))
    full = schema.encode(b, schema.Encoding(normals01=True, spp=True), spp=4)
    del b["normal"], b["emission"]
    part = schema.encode(b, schema.Encoding(normals01=True, spp=True), spp=4)
    names = schema.names(schema.Encoding(spp=True))
    assert part.shape == full.shape and len(names) == part.shape[0]
    assert np.all(part[names.index("normal.Y")] == 0.5)          # background 0 -> (0 + 1) / 2
    assert np.all(part[names.index("emission.G")] == 0.0)         # log1p(0)
    assert np.all(part[names.index("normal.variance")] == 0.0)    # no buffer, no variance feature
    np.testing.assert_array_equal(part[names.index("color.R")], full[names.index("color.R")])
