"""Config loading: defaults, overrides, errors that name the key, docs in sync with the code."""
import json
import re
from pathlib import Path

import pytest

from mcdenoise.pipeline.config import ConfigError, documentation_markdown, load_config, to_dict

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_configs_load(path):
    cfg = load_config(path)
    assert cfg.dataset.scenes >= 1


def test_paper_config_has_paper_settings():
    d = load_config(ROOT / "configs" / "paper.yaml").dataset
    assert (d.scenes, d.frames, d.resolution, d.gt_spp, d.stack_spp, d.stacks) == (5650, 8, [256, 256], 4096, 4, 16)


def test_sequence_config_renders_8_frame_sequences_into_its_own_store():
    from mcdenoise.pipeline.config import run_dir
    cfg = load_config(ROOT / "configs" / "sequence.yaml")
    d = cfg.dataset
    assert (d.frames, d.scenes) == (8, 24) and d.resolution == [64, 48]
    assert cfg.scene.interior_probability == 0.4 and d.val_fraction == d.test_fraction == 0.25
    assert cfg.store == "data/sequence" and Path(run_dir(cfg, "cleaner")).parent == Path("runs/sequence")
    assert cfg.diffusion.crop % 16 == 0 and cfg.diffusion.crop <= min(d.resolution)


def test_overrides_are_typed_and_nested():
    cfg = load_config(ROOT / "configs" / "tiny.yaml", ["dataset.scenes=5", "render.max_depth=3",
                                                       "dataset.resolution=[16, 8]", "scene.fov=[30, 40]"])
    assert cfg.dataset.scenes == 5 and cfg.render.max_depth == 3
    assert cfg.dataset.resolution == [16, 8]
    assert cfg.scene.fov == [30, 40]


def test_int_is_accepted_for_float():
    assert load_config(None, ["scene.camera_move=1"]).scene.camera_move == 1.0


def test_exponent_without_a_dot_is_a_float_not_a_string():
    # YAML 1.1 reads "1e-4" as a string; the float fields take it as the number a user means.
    cfg = load_config(None, ["diffusion.lr=1e-4", "clean.lr=2E-3"])
    assert cfg.diffusion.lr == 1e-4 and cfg.clean.lr == 2e-3
    with pytest.raises(ConfigError, match=r"diffusion\.lr"):
        load_config(None, ["diffusion.lr=fast"])


def test_unknown_key_names_file_and_key(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("dataset:\n  scenez: 3\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml.*dataset\.scenez"):
        load_config(path)


def test_unknown_override_key():
    with pytest.raises(ConfigError, match=r"render\.maxdepth"):
        load_config(None, ["render.maxdepth=3"])


def test_wrong_type_names_key():
    with pytest.raises(ConfigError, match=r"dataset\.scenes: expected int, got str"):
        load_config(None, ["dataset.scenes=many"])


def test_bool_is_not_an_int():
    with pytest.raises(ConfigError, match=r"dataset\.frames"):
        load_config(None, ["dataset.frames=true"])


def test_value_checks():
    with pytest.raises(ConfigError, match=r"dataset\.resolution"):
        load_config(None, ["dataset.resolution=[0, 4]"])
    with pytest.raises(ConfigError, match=r"executor\.kind"):
        load_config(None, ["executor.kind=slurm"])


def test_malformed_yaml_names_file(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("dataset: [1, 2\n")
    with pytest.raises(ConfigError, match="broken.yaml"):
        load_config(path)


def test_yaml_is_loaded_safely(tmp_path):
    path = tmp_path / "evil.yaml"
    path.write_text("seed: !!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(path)


def test_every_key_documented_in_configs_readme():
    assert (ROOT / "configs" / "README.md").read_text() == documentation_markdown(), \
        "configs/README.md is stale: regenerate with `python -m pipeline config --doc > configs/README.md`"


def test_overrides_may_follow_options(capsys):
    """`key=value` after an option still overrides (argparse alone stops the list at the option);
    stray options and non-override words are still refused."""
    import yaml

    from mcdenoise.pipeline.cli import main

    assert main(["config", "clean.lr=0.5", "--config", "configs/tiny.yaml", "clean.epochs=7", "clean.lr=0.25"]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["clean"]["epochs"] == 7 and printed["clean"]["lr"] == 0.25   # the later override wins
    for stray in (["--bogus"], ["scene.xml"]):
        with pytest.raises(SystemExit) as exc:
            main(["config", "clean.lr=0.5", "--config", "configs/tiny.yaml", *stray])
        assert exc.value.code == 2
        assert f"unrecognized arguments: {stray[0]}" in capsys.readouterr().err



def test_a_scene_file_may_stand_anywhere_among_the_overrides(capsys):
    """`render-scene X.xml --store S key=value` and `render-scene --store S X.xml key=value` say the same;
    no scene file or two of them is one line and status 2."""
    from mcdenoise.pipeline.cli import build_parser, parse_args

    parser = build_parser()
    orders = (["render-scene", "a/x.xml", "--store", "st", "dataset.gt_spp=64", "seed=3"],
              ["render-scene", "--store", "st", "a/x.xml", "dataset.gt_spp=64", "seed=3"],
              ["render-scene", "--store", "st", "dataset.gt_spp=64", "a/x.xml", "seed=3"],
              ["render-scene", "dataset.gt_spp=64", "--store", "st", "seed=3", "a/x.xml"])
    for argv in orders:
        args = parse_args(parser, argv)
        assert (args.scene, args.overrides, args.store) == ("a/x.xml", ["dataset.gt_spp=64", "seed=3"], "st"), argv
    for argv in (["render-scene", "--store", "st", "seed=3", "dataset.gt_spp=64"],
                 ["render-scene", "a.xml", "b.xml", "seed=3"]):
        with pytest.raises(SystemExit) as exc:
            parse_args(parser, argv)
        assert exc.value.code == 2 and "expected one scene file and key=value overrides" in capsys.readouterr().err

# ---- sections: each checks its own keys; the trainer sections share TrainingConfig ---------------

SHARED = {"epochs", "batch_size", "crop", "lr", "grad_clip", "nan_limit", "time_budget_s", "device"}
# Every key of each trainer section, written out: a YAML file, a `section.key=value` or a run fingerprint
# keeps working.
TRAINER_KEYS = {
    "clean": SHARED | {"weight_decay", "crops_per_frame", "smape_eps", "kernel_size", "dilations", "channels",
                       "embed_channels", "affinity_channels", "range_term", "range_patch", "tile"},
    "afgsa": SHARED | {"target", "crops_per_frame", "lr_critic", "adv_weight", "gp_weight", "channels",
                       "extractor_channels", "blocks", "heads", "block_size", "halo", "critic_channels",
                       "critic_levels", "tile"},
    "diffusion": SHARED | {"base", "base_network", "extra_stores", "init", "model", "crops_per_frame", "epoch_steps",
                           "history", "history_dropout",
                           "weight_decay", "warmup_steps", "precision", "shipped", "name", "schedule",
                           "residual_scale", "snr_gamma", "snr_floor", "hdr_weight", "dropout", "t_focus",
                           "train_steps", "steps", "start", "samples", "skip", "ema", "val_frames", "loader_workers",
                           "keep_epochs"},
    "oidn_ft": SHARED | {"network", "crops_per_frame", "epoch_steps", "lr_end", "warmup_steps", "weight_decay",
                         "loss", "l2sp", "distill", "diversify", "trainable", "augment", "blend", "val_frames",
                         "target", "fine_levels"},
}
TRAINER_DEFAULTS = {   # section: (epochs, lr), the defaults each section gives the shared keys without one
    "clean": (12, 1e-3), "afgsa": (12, 5e-4), "diffusion": (16, 2e-4),
    "oidn_ft": (30, 5e-5),
}


@pytest.mark.parametrize("section", sorted(TRAINER_KEYS))
def test_trainer_sections_keep_their_keys_and_defaults(section):
    values = to_dict(load_config(None))[section]
    assert set(values) == TRAINER_KEYS[section]
    assert (values["epochs"], values["lr"]) == TRAINER_DEFAULTS[section]
    assert {k: values[k] for k in SHARED - {"epochs", "lr"}} == {
        "batch_size": 8, "crop": 64, "grad_clip": 1.0, "nan_limit": 10, "time_budget_s": 0.0, "device": "auto"}


def test_the_diffusion_defaults_are_the_shipped_models_recipe():
    """make train trains what ships: every setting train/shipped/model.json records is the default."""
    from mcdenoise.train.model import SHIPPED_MODEL
    settings = json.loads((SHIPPED_MODEL / "model.json").read_text())["settings"]
    d = to_dict(load_config(None))["diffusion"]
    recipe = {k: v for k, v in settings.items() if k not in ("base_sha256", "formulation", "seed", "spp")}
    assert {k: d[k] for k in recipe} == recipe
    meta = json.loads((SHIPPED_MODEL / "model.json").read_text())
    assert (d["base"], d["base_network"], meta["base_blend"]) == ("oidn", meta["base_network"], 0.0)


def test_ship_yaml_is_the_shipped_models_recipe_on_its_data():
    """configs/ship.yaml holds the recipe itself (not only a model card's command line): its diffusion section
    and seed give the shipped model's settings."""
    from mcdenoise.train.model import SHIPPED_MODEL
    meta = json.loads((SHIPPED_MODEL / "model.json").read_text())
    cfg = load_config(ROOT / "configs" / "ship.yaml")
    d = to_dict(cfg)["diffusion"]
    recipe = {k: v for k, v in meta["settings"].items() if k not in ("base_sha256", "formulation", "seed", "spp")}
    assert {k: d[k] for k in recipe} == recipe and cfg.seed == meta["settings"]["seed"]
    assert cfg.store == meta["store"] and (d["base"], d["base_network"]) == ("oidn", meta["base_network"])


def test_ship_rooms_trains_with_ship_yamls_recipe():
    """configs/ship_rooms.yaml changes the scenes, not the training: its clean, oidn_ft and diffusion sections
    are configs/ship.yaml's, so the two cannot drift apart."""
    ship, rooms = (to_dict(load_config(ROOT / "configs" / f"{name}.yaml")) for name in ("ship", "ship_rooms"))
    for section in ("clean", "oidn_ft", "diffusion"):
        assert rooms[section] == ship[section], f"configs/ship_rooms.yaml: section {section} differs from ship.yaml's"
    assert rooms["dataset"] != ship["dataset"] and rooms["scene"] != ship["scene"]


@pytest.mark.parametrize("section", sorted(TRAINER_KEYS))
@pytest.mark.parametrize("override", ["batch_size=0", "crop=0", "nan_limit=0", "grad_clip=-1", "time_budget_s=-5",
                                      "lr=0"])
def test_a_bad_shared_setting_is_named_with_its_section(section, override):
    key = override.split("=")[0]
    with pytest.raises(ConfigError, match=rf"<defaults>: {section}\.{key}: must be "):
        load_config(None, [f"{section}.{override}"])


def test_epochs_zero_is_refused():
    for section in ("clean", "afgsa", "diffusion", "oidn_ft"):
        with pytest.raises(ConfigError, match=rf"{section}\.epochs: must be >= 1"):
            load_config(None, [f"{section}.epochs=0"])


def test_section_checks_keep_their_messages():
    for override, message in [
        ("oidn_ft.crop=40", r"oidn_ft\.crop: must be a positive multiple of 16"),
        ("afgsa.heads=3", r"afgsa\.channels/heads: 32 channels must split into 3 heads"),
        ("dataset.stress_split=both", r"dataset\.stress_split: expected 'stress' or 'mixed', got 'both'"),
        ("diffusion.precision=fp16", r"diffusion\.precision: expected 'auto', 'fp32' or 'bf16', got 'fp16'"),
        ("diffusion.base=", r"diffusion\.base: expected 'oidn', 'oidn_ft' or a \.tza file"),
        ("diffusion.crop=40", r"diffusion\.crop: must be a multiple of 16"),
        ("eval.equal_time=never", r"eval\.equal_time: expected 'render', 'pool' or 'none', got 'never'"),
    ]:
        with pytest.raises(ConfigError, match=message):
            load_config(None, [override])


# ---- the formulation keys: one set of rules for the config and train.sampler -----------------

def test_skip_counts_in_the_samplers_steps():
    d = load_config(None, ["diffusion.steps=50", "diffusion.skip=30"]).diffusion
    assert (d.steps, d.skip) == (50, 30)
    with pytest.raises(ConfigError, match=r"diffusion\.skip: need 0 <= skip < steps \(50\), got 50"):
        load_config(None, ["diffusion.steps=50", "diffusion.skip=50"])
    with pytest.raises(ConfigError, match=r"diffusion\.steps: need 1 <= steps <= 1000, got 1001"):
        load_config(None, ["diffusion.steps=1001"])


def test_retired_keys_are_unknown():
    """The stand-in stack's keys are gone: a config that still sets one is told so, naming the key."""
    for key, named in (("diffusion.prediction=epsilon", "diffusion.prediction"),
                       ("diffusion.estimate=none", "diffusion.estimate"), ("diffusion.train_base=true",
                       "diffusion.train_base"), ("diffusion.tonemap=log", "diffusion.tonemap"),
                       ("pretrain.epochs=1", "pretrain")):
        with pytest.raises(ConfigError, match=r"unknown config key " + re.escape(named) + " "):
            load_config(None, [key])


@pytest.mark.parametrize("key", ["polished_probability", "texture_probability", "walls_probability"])
def test_a_scene_probability_outside_zero_one_is_named(key):
    with pytest.raises(ConfigError, match=rf"scene\.{key}: expected a probability in \[0, 1\], got 1\.5"):
        load_config(None, [f"scene.{key}=1.5"])
    assert getattr(load_config(None, [f"scene.{key}=1"]).scene, key) == 1
