"""Config loading: defaults, overrides, errors that name the key, docs in sync with the code."""
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

    from mcdenoise.pipeline.__main__ import main

    assert main(["config", "clean.lr=0.5", "--config", "configs/tiny.yaml", "clean.epochs=7", "clean.lr=0.25"]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["clean"]["epochs"] == 7 and printed["clean"]["lr"] == 0.25   # the later override wins
    for stray in (["--bogus"], ["scene.xml"]):
        with pytest.raises(SystemExit) as exc:
            main(["config", "clean.lr=0.5", "--config", "configs/tiny.yaml", *stray])
        assert exc.value.code == 2
        assert f"unrecognized arguments: {stray[0]}" in capsys.readouterr().err


# ---- sections: each checks its own keys; the trainer sections share TrainingConfig ---------------

SHARED = {"epochs", "batch_size", "crop", "lr", "grad_clip", "nan_limit", "time_budget_s", "device"}
# Every key each trainer section had before TrainingConfig (pretrain: plus the five it borrowed from
# diffusion), written out: a YAML file, a `section.key=value` or a run fingerprint keeps working.
TRAINER_KEYS = {
    "clean": SHARED | {"weight_decay", "crops_per_frame", "smape_eps", "kernel_size", "dilations", "channels",
                       "embed_channels", "affinity_channels", "range_term", "range_patch", "tile"},
    "afgsa": SHARED | {"target", "crops_per_frame", "lr_critic", "adv_weight", "gp_weight", "channels",
                       "extractor_channels", "blocks", "heads", "block_size", "halo", "critic_channels",
                       "critic_levels", "tile"},
    "diffusion": SHARED | {"base", "tonemap", "crops_per_frame", "epoch_steps", "weight_decay", "warmup_steps",
                           "train_base", "control", "precision", "shipped", "name", "prediction", "schedule",
                           "estimate", "isik_run", "residual", "residual_scale", "snr_gamma", "snr_floor",
                           "hdr_weight", "dropout", "loss_norm", "t_focus", "train_steps", "sampler", "steps",
                           "start", "samples", "skip", "threshold_ratio", "variance", "ema", "pack", "val_frames",
                           "val_skip", "tile", "tile_overlap",
                           "init",    # added after TrainingConfig: a warm start from a trained model folder
                           "extra_stores",    # more stores' train splits beside the config's
                           "base_network"},   # which of OIDN's networks the Control Module sits on
    "pretrain": SHARED | {"channels", "layers_per_block", "images", "crops_per_image", "weight_decay", "scales",
                          "noise", "fireflies", "real", "out", "warmup_steps", "precision"},
    "oidn_ft": SHARED | {"network", "crops_per_frame", "epoch_steps", "lr_end", "warmup_steps", "weight_decay",
                         "loss", "l2sp", "distill", "diversify", "trainable", "augment", "blend", "val_frames",
                         "target", "fine_levels"},
}
TRAINER_DEFAULTS = {   # section: (epochs, lr), the defaults each section gives the shared keys without one
    "clean": (12, 1e-3), "afgsa": (12, 5e-4), "diffusion": (100, 2e-5), "pretrain": (100, 2e-4),
    "oidn_ft": (30, 5e-5),
}


@pytest.mark.parametrize("section", sorted(TRAINER_KEYS))
def test_trainer_sections_keep_their_keys_and_defaults(section):
    values = to_dict(load_config(None))[section]
    assert set(values) == TRAINER_KEYS[section]
    assert (values["epochs"], values["lr"]) == TRAINER_DEFAULTS[section]
    assert {k: values[k] for k in SHARED - {"epochs", "lr"}} == {
        "batch_size": 8, "crop": 64, "grad_clip": 1.0, "nan_limit": 10, "time_budget_s": 0.0, "device": "auto"}


def test_pretrain_has_the_defaults_it_borrowed_from_diffusion():
    cfg = load_config(None)
    for key in ("warmup_steps", "grad_clip", "nan_limit", "precision", "device"):
        assert getattr(cfg.pretrain, key) == getattr(cfg.diffusion, key), key


@pytest.mark.parametrize("section", sorted(TRAINER_KEYS))
@pytest.mark.parametrize("override", ["batch_size=0", "crop=0", "nan_limit=0", "grad_clip=-1", "time_budget_s=-5",
                                      "lr=0"])
def test_a_bad_shared_setting_is_named_with_its_section(section, override):
    key = override.split("=")[0]
    with pytest.raises(ConfigError, match=rf"<defaults>: {section}\.{key}: must be "):
        load_config(None, [f"{section}.{override}"])


def test_epochs_zero_is_refused_except_for_pretrain():
    for section in ("clean", "afgsa", "diffusion", "oidn_ft"):
        with pytest.raises(ConfigError, match=rf"{section}\.epochs: must be >= 1"):
            load_config(None, [f"{section}.epochs=0"])
    assert load_config(None, ["pretrain.epochs=0"]).pretrain.epochs == 0   # writes the initialised base
    with pytest.raises(ConfigError, match=r"pretrain\.epochs: must be >= 0"):
        load_config(None, ["pretrain.epochs=-1"])


def test_section_checks_keep_their_messages():
    for override, message in [
        ("oidn_ft.crop=40", r"oidn_ft\.crop: must be a positive multiple of 16"),
        ("afgsa.heads=3", r"afgsa\.channels/heads: 32 channels must split into 3 heads"),
        ("dataset.stress_split=both", r"dataset\.stress_split: expected 'stress' or 'mixed', got 'both'"),
        ("pretrain.precision=fp16", r"pretrain\.precision: expected 'auto', 'fp32' or 'bf16', got 'fp16'"),
        ("diffusion.tile=64", r"diffusion\.tile/tile_overlap: need tile > 2 \* tile_overlap"),
        ("eval.equal_time=never", r"eval\.equal_time: expected 'render', 'pool' or 'none', got 'never'"),
    ]:
        with pytest.raises(ConfigError, match=message):
            load_config(None, [override])


# ---- the formulation keys: one set of rules for the config and train.formulation -----------------

PAPER = ["diffusion.prediction=epsilon", "diffusion.schedule=if", "diffusion.residual=false",
         "diffusion.estimate=none"]


def test_refine_skip_counts_in_its_own_steps():
    d = load_config(None, ["diffusion.steps=50", "diffusion.skip=30"]).diffusion
    assert (d.steps, d.skip) == (50, 30)
    with pytest.raises(ConfigError, match=r"diffusion\.skip: need 0 <= skip < steps \(50\), got 50"):
        load_config(None, ["diffusion.steps=50", "diffusion.skip=50"])
    with pytest.raises(ConfigError, match=r"diffusion\.steps: need 1 <= steps <= 1000, got 1001"):
        load_config(None, ["diffusion.steps=1001"])
    # val_skip is the paper formulation's: unused by the refine formulation, so not refused there
    assert load_config(None, ["diffusion.val_skip=40"]).diffusion.val_skip == 40


def test_paper_skips_count_in_super27():
    assert load_config(None, [*PAPER, "diffusion.skip=12"]).diffusion.skip == 12
    for key in ("skip", "val_skip"):
        with pytest.raises(ConfigError, match=rf"<defaults>: diffusion\.{key}: the paper formulation skips 0\.\.26"):
            load_config(None, [*PAPER, f"diffusion.{key}=27"])


def test_a_formulation_error_is_a_config_error_naming_the_key():
    with pytest.raises(ConfigError, match=r"diffusion\.residual: true needs a first estimate"):
        load_config(None, ["diffusion.estimate=none"])
    with pytest.raises(ConfigError, match=r"diffusion\.prediction: epsilon with diffusion\.schedule=zero_snr"):
        load_config(None, ["diffusion.prediction=epsilon"])
    with pytest.raises(ConfigError, match=r"diffusion\.estimate: the paper formulation"):
        load_config(None, ["diffusion.prediction=epsilon", "diffusion.schedule=if", "diffusion.residual=false"])


@pytest.mark.parametrize("key", ["polished_probability", "texture_probability", "walls_probability"])
def test_a_scene_probability_outside_zero_one_is_named(key):
    with pytest.raises(ConfigError, match=rf"scene\.{key}: expected a probability in \[0, 1\], got 1\.5"):
        load_config(None, [f"scene.{key}=1.5"])
    assert getattr(load_config(None, [f"scene.{key}=1"]).scene, key) == 1
