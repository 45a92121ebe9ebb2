"""Run folders (``pipeline.runs``): one naming rule for every trainer, and the per-stage spellings
that delegate to it."""
import pytest

from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.runs import pick_device, run_dir


def test_every_model_has_its_folder(tmp_path):
    cfg = load_config(None, [f"runs={tmp_path}"])
    assert run_dir(cfg, "cleaner") == tmp_path / "cleaner"
    assert run_dir(cfg, "isik", 4) == tmp_path / "isik_spp4"
    assert run_dir(cfg, "isik", "any") == tmp_path / "isik_sppany"
    assert run_dir(cfg, "afgsa", 16) == tmp_path / "afgsa_spp16"
    assert run_dir(cfg, "diffusion", 64) == tmp_path / "diffusion_spp64"
    assert run_dir(cfg, "diffusion", "any", "paper") == tmp_path / "diffusion_sppany_paper"
    with pytest.raises(ValueError, match="model must be one of"):
        run_dir(cfg, "oidn", 4)


def test_settings_that_name_the_folder(tmp_path):
    cfg = load_config(None, [f"runs={tmp_path}", "afgsa.target=gt1", "diffusion.name=wide", "diffusion.control=false",
                             "diffusion.train_base=true"])
    assert run_dir(cfg, "afgsa", 4) == tmp_path / "afgsa_gt1_spp4"
    assert run_dir(cfg, "diffusion", 4) == tmp_path / "diffusion_spp4_wide_base_only"
    assert run_dir(cfg, "diffusion", 4, "") == tmp_path / "diffusion_spp4_base_only"


def test_stage_spellings_delegate(tmp_path):
    from mcdenoise.clean.train import run_dir as clean_run_dir
    from mcdenoise.train.model import run_dir as diffusion_run_dir

    cfg = load_config(None, [f"runs={tmp_path}"])
    assert clean_run_dir(cfg) == run_dir(cfg, "cleaner")
    assert clean_run_dir(cfg, "baseline", 4) == run_dir(cfg, "isik", 4)
    assert clean_run_dir(cfg, "afgsa", "any") == run_dir(cfg, "afgsa", "any")
    assert diffusion_run_dir(cfg, 16) == run_dir(cfg, "diffusion", 16)
    with pytest.raises(ValueError, match="mode must be 'cleaner', 'baseline' or 'afgsa'"):
        clean_run_dir(cfg, "isik", 4)


def test_pick_device():
    assert str(pick_device("cpu")) == "cpu"
    assert pick_device("auto").type in ("cpu", "cuda")
