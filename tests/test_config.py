"""Config loading: defaults, overrides, errors that name the key, docs in sync with the code."""
from pathlib import Path

import pytest

from mcdenoise.pipeline.config import ConfigError, documentation_markdown, load_config

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["default", "tiny", "paper"])
def test_shipped_configs_load(name):
    cfg = load_config(ROOT / "configs" / f"{name}.yaml")
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
