"""Trained models on disk (pipeline/weights.py): one tag per kind, refused with one line otherwise."""
import pytest
import torch

from mcdenoise.pipeline import weights
from mcdenoise.pipeline.errors import CheckpointError


def test_a_saved_model_reads_back_as_its_kind_only(tmp_path):
    tensors = {"w": torch.arange(6, dtype=torch.float32).reshape(2, 3)}
    weights.save(tmp_path / "m", "oidn_ft", tensors, {"epoch": 3, "format": "stale"}, weights="x.safetensors")
    record = weights.read_record(tmp_path / "m", ("oidn_control", "oidn_ft"), "retrain")
    assert record == {"format": "mcdenoise-oidn-ft", "epoch": 3} and weights.kind(tmp_path / "m") == "oidn_ft"
    assert torch.equal(weights.load_tensors(tmp_path / "m" / "x.safetensors")["w"], tensors["w"])
    with pytest.raises(CheckpointError, match=r"m/model.json: format 'mcdenoise-oidn-ft', not a oidn_control model; run it"):
        weights.read_record(tmp_path / "m", "oidn_control", "run it")
    with pytest.raises(CheckpointError, match=r"nothing: no trained model here \(model.json missing\); train"):
        weights.read_record(tmp_path / "nothing", "oidn_control", "train")
    assert weights.kind(tmp_path / "nothing") is None


def test_a_changed_prior_and_a_pickle_are_refused(tmp_path):
    weights.check_sha256(b"abc", "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad", "x", "y")
    with pytest.raises(CheckpointError, match="the base changed since the model was trained .*; retrain"):
        weights.check_sha256(b"abd", "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad",
                             "the base", "retrain")
    torch.save({"w": torch.zeros(2)}, tmp_path / "p.safetensors")
    with pytest.raises(CheckpointError, match="p.safetensors: not a usable safetensors checkpoint"):
        weights.load_tensors(tmp_path / "p.safetensors")
