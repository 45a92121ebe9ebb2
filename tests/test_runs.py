"""Run folders (``pipeline.config``): one naming rule for every trainer, and the per-stage spellings
that delegate to it."""
from pathlib import Path

import pytest

from mcdenoise.pipeline.config import find_run, load_config, pick_device, run_candidates, run_dir

from .helpers import TINY, cli

ROOT = Path(__file__).resolve().parents[1]


def test_every_model_has_its_folder(tmp_path):
    cfg = load_config(None, [f"runs={tmp_path}"])
    assert run_dir(cfg, "cleaner") == tmp_path / "cleaner"
    assert run_dir(cfg, "isik", 4) == tmp_path / "isik_spp4"
    assert run_dir(cfg, "isik", "any") == tmp_path / "isik_sppany"
    assert run_dir(cfg, "afgsa", 16) == tmp_path / "afgsa_spp16"
    assert run_dir(cfg, "diffusion", 64) == tmp_path / "diffusion_spp64"
    assert run_dir(cfg, "diffusion", "any", "large") == tmp_path / "diffusion_sppany_large"
    with pytest.raises(ValueError, match="model must be one of"):
        run_dir(cfg, "oidn", 4)


def test_settings_that_name_the_folder(tmp_path):
    cfg = load_config(None, [f"runs={tmp_path}", "afgsa.target=gt1", "diffusion.name=wide"])
    assert run_dir(cfg, "afgsa", 4) == tmp_path / "afgsa_gt1_spp4"
    assert run_dir(cfg, "diffusion", 4) == tmp_path / "diffusion_spp4_wide"
    assert run_dir(cfg, "diffusion", 4, "") == tmp_path / "diffusion_spp4"


def test_stage_spellings_delegate(tmp_path):
    from mcdenoise.clean.train import run_dir as clean_run_dir
    from mcdenoise.train.model import run_dir as diffusion_run_dir

    cfg = load_config(None, [f"runs={tmp_path}"])
    assert clean_run_dir(cfg) == run_dir(cfg, "cleaner")
    assert clean_run_dir(cfg, "baseline", 4) == run_dir(cfg, "isik", 4)
    assert diffusion_run_dir(cfg, 16) == run_dir(cfg, "diffusion", 16)
    for mode in ("isik", "afgsa"):
        with pytest.raises(ValueError, match="mode must be 'cleaner' or 'baseline'"):
            clean_run_dir(cfg, mode, 4)


def test_find_run_takes_the_own_run_then_the_any_spp_run(tmp_path):
    cfg = load_config(None, [f"runs={tmp_path}"])
    assert run_candidates(cfg, "afgsa", 4) == [tmp_path / "afgsa_spp4", tmp_path / "afgsa_sppany"]
    assert run_candidates(cfg, "afgsa", "any") == [tmp_path / "afgsa_sppany"]
    assert find_run(cfg, "afgsa", 4, "model.safetensors") is None
    shipped = tmp_path / "shipped"
    shipped.mkdir()
    (shipped / "model.json").write_text("{}")
    assert find_run(cfg, "diffusion", 4, "model.json", fallback=shipped) == shipped
    for name in ("afgsa_sppany", "diffusion_sppany"):
        (tmp_path / name).mkdir()
    (tmp_path / "afgsa_sppany" / "model.safetensors").write_bytes(b"")
    (tmp_path / "diffusion_sppany" / "model.json").write_text("{}")
    assert find_run(cfg, "afgsa", 4, "model.safetensors") == tmp_path / "afgsa_sppany"
    assert find_run(cfg, "diffusion", 4, "model.json", fallback=shipped) == tmp_path / "diffusion_sppany"
    # the any-spp run serves only the counts it says it trained on; the own run always
    assert find_run(cfg, "afgsa", 4, "model.safetensors", serves=lambda folder: False) is None
    (tmp_path / "afgsa_spp4").mkdir()
    (tmp_path / "afgsa_spp4" / "model.safetensors").write_bytes(b"")
    assert find_run(cfg, "afgsa", 4, "model.safetensors", serves=lambda folder: False) == tmp_path / "afgsa_spp4"
    assert find_run(cfg, "afgsa", "any", "model.safetensors", serves=lambda folder: False) == tmp_path / "afgsa_sppany"


def test_pick_device():
    assert str(pick_device("cpu")) == "cpu"
    assert pick_device("auto").type in ("cpu", "cuda")


def test_each_shipped_config_owns_its_runs_and_reports():
    """No two configs of configs/ share a runs folder (nor, so, a report folder): a config without ``runs:``
    gets runs/<its store's folder name>."""
    configs = sorted((ROOT / "configs").glob("*.yaml"))
    runs = {p.name: load_config(p).runs for p in configs}
    assert len(set(runs.values())) == len(runs), runs
    assert runs["tiny.yaml"] == "runs/tiny" and runs["default.yaml"] == "runs/default"
    assert load_config(None, ["store=elsewhere/mine"]).runs == "runs/mine"
    assert load_config(None, ["store=elsewhere/mine", "runs=r"]).runs == "r"


def test_a_diffusion_run_trained_on_another_store_is_passed_over_in_one_line(tmp_path, capsys):
    """A run of another config in the runs folder (its model.json names another store) is not this config's
    model: the shipped one serves, and one line says so; the run of this store serves."""
    import json
    import shutil

    from mcdenoise.train.model import SHIPPED_MODEL, find_run as find_diffusion_run

    run = tmp_path / "runs" / "diffusion_sppany"
    shutil.copytree(SHIPPED_MODEL, run)
    record = json.loads((run / "model.json").read_text())
    (run / "model.json").write_text(json.dumps({**record, "store": str(tmp_path / "other_store")}))
    cfg = load_config(None, [f"store={tmp_path / 'mine'}", f"runs={tmp_path / 'runs'}"])
    assert find_diffusion_run(cfg, 4) == SHIPPED_MODEL
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 1 and f"{run} was trained on {tmp_path / 'other_store'}" in out[0] and "using" in out[0]
    (run / "model.json").write_text(json.dumps({**record, "store": str(tmp_path / "mine")}))
    assert find_diffusion_run(cfg, 4) == run


def test_export_without_a_run_names_the_make_line_of_its_config(tmp_path):
    """The hint is a command that trains what the export reads: the same config's runs."""
    proc = cli("export", "--config", TINY, f"runs={tmp_path}", "--spp", "4", "--out", tmp_path / "model", check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].endswith(f"run `make train SPP=4 CONFIG={TINY}` first")
    assert not (tmp_path / "model").exists()
    proc = cli("export", "--format", "oidn", f"runs={tmp_path}", check=False)
    assert proc.returncode == 2 and "run `make train MODEL=oidn_ft SPP=any` first" in proc.stderr, proc.stderr


def test_eval_loads_the_run_that_diffusion_name_named(tmp_path):
    """`eval diffusion.name=x` scores the run `train diffusion.name=x` wrote as ``ours``; a method's own variant
    (``ours_y``) still picks its run."""
    from mcdenoise.evaluate.methods import Loader, parse

    for name in ("diffusion_sppany", "diffusion_sppany_x", "diffusion_sppany_y"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "model.json").write_text("{}")
    cfg = load_config(None, [f"runs={tmp_path}", "diffusion.name=x"])
    loader = Loader(cfg)
    assert loader.diffusion_folder(4, parse("ours").variant) == tmp_path / "diffusion_sppany_x"
    assert loader.diffusion_folder(4, parse("ours_y").variant) == tmp_path / "diffusion_sppany_y"
    unnamed = Loader(load_config(None, [f"runs={tmp_path}"]))
    assert unnamed.diffusion_folder(4, parse("ours").variant) == tmp_path / "diffusion_sppany"


def test_diffusion_model_names_the_model_ours_runs_whatever_the_runs_folder_holds(tmp_path):
    """``diffusion.model`` scores a model trained on another store (its model.json names that store) on this
    one: the lookup without a variant returns it, past the runs folder's own run; ``ours_y`` still picks its run;
    a folder without model.json is an error naming the key."""
    import json

    from mcdenoise.evaluate.methods import Loader, MethodUnavailable, parse

    for name, store in (("diffusion_sppany", "mine"), ("diffusion_sppany_y", "mine"), ("elsewhere", "other")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "model.json").write_text(json.dumps({"store": str(tmp_path / store)}))
    cfg = load_config(None, [f"store={tmp_path / 'mine'}", f"runs={tmp_path}",
                             f"diffusion.model={tmp_path / 'elsewhere'}"])
    loader = Loader(cfg)
    assert loader.diffusion_folder(4, parse("ours").variant) == tmp_path / "elsewhere"
    assert loader.diffusion_folder(16, parse("ours").variant) == tmp_path / "elsewhere"
    assert loader.diffusion_folder(4, parse("ours_y").variant) == tmp_path / "diffusion_sppany_y"
    missing = Loader(load_config(None, [f"runs={tmp_path}", f"diffusion.model={tmp_path / 'none'}"]))
    with pytest.raises(MethodUnavailable, match=r"^diffusion\.model: .*none has no model\.json"):
        missing.diffusion_folder(4, parse("ours").variant)
