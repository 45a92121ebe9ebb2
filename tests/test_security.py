"""Untrusted inputs: checkpoints, configs, scene files and store manifests from users.

- The code base never unpickles: no ``pickle``/``marshal``/``shelve``/``dill``/``joblib`` loads,
  ``torch.load`` only with ``weights_only=True``, ``numpy.load`` never with
  ``allow_pickle=True``, YAML only through ``safe_load`` (checked on the syntax tree of every
  module, so new code such as the diffusion trainer is held to it too).
- A pickle "checkpoint" that would run code when unpickled is refused with an error naming the
  file, and its code does not run (a marker file it would create stays absent).
- A ``!!python/object`` config (file or override) is refused naming the file; its code does not run.
- Scene XML and names from users cannot make the renderer write outside the store: ``--name``
  with path components is refused, a film ``filename`` in the XML writes nothing, and store
  manifests naming scenes like ``../../x`` are refused before anything is read or written.
"""
from __future__ import annotations

import ast
import json
import os
from pathlib import Path

import pytest
import torch

from mcdenoise.pipeline.exr import StoreError
from mcdenoise.pipeline.store import Store
from tests.helpers import TINY, cli

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "render", "clean", "train", "evaluate")


def project_modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def _dotted(node: ast.AST) -> str:
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value)}.{node.attr}"
    if isinstance(node, ast.Name):
        return node.id
    return "?"


def _kw(call: ast.Call, name: str):
    for kw in call.keywords:
        if kw.arg == name:
            return kw.value.value if isinstance(kw.value, ast.Constant) else "<expr>"
    return None


def _shown(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def unsafe_calls(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [a.name for a in node.names] + ([node.module] if isinstance(node, ast.ImportFrom) and node.module else [])
            for n in names:
                if n.split(".")[0] in ("pickle", "cPickle", "dill", "shelve", "marshal", "joblib", "cloudpickle"):
                    found.append(f"{_shown(path)}:{node.lineno}: imports {n}")
        if not isinstance(node, ast.Call):
            continue
        name = _dotted(node.func)
        where = f"{_shown(path)}:{node.lineno}: {name}"
        if name.endswith("torch.load"):
            if _kw(node, "weights_only") is not True:
                found.append(f"{where} without weights_only=True")
        if name in ("np.load", "numpy.load") and _kw(node, "allow_pickle") not in (None, False):
            found.append(f"{where} with allow_pickle")
        if name in ("yaml.load", "yaml.load_all", "yaml.unsafe_load", "yaml.full_load", "yaml.unsafe_load_all"):
            found.append(f"{where}: use yaml.safe_load")
        if name.endswith(("pickle.load", "pickle.loads")):
            found.append(where)
    return found


def test_code_base_never_unpickles():
    modules = project_modules()
    assert len(modules) > 30
    problems = [p for m in modules for p in unsafe_calls(m)]
    assert problems == [], "\n".join(problems)


def test_the_checker_catches_what_it_should(tmp_path):
    # Source text only: parsed by the checker, never imported or run. Written to tmp_path so the
    # repository's tree is never touched by a test.
    bad = tmp_path / "probe.py"
    bad.write_text("import torch, yaml, pickle\nimport numpy as np\n"
                   "torch.load('x')\ntorch.load('x', weights_only=False)\nyaml.load('a')\n"
                   "np.load('x', allow_pickle=True)\npickle.loads(b'')\ntorch.load('x', weights_only=True)\n")
    found = unsafe_calls(bad)
    assert len(found) == 6, found      # the import, 2 torch.load, yaml.load, np.load, pickle.loads


class Evil:
    """Unpickling this runs ``touch MARKER``."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _evil_checkpoint(path: Path, marker: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"model": Evil(marker)}, path)


def test_pickle_model_checkpoint_is_refused(tmp_path):
    from mcdenoise.clean.model import load_model
    from mcdenoise.clean.train import build_model, save_best
    from tests.helpers import tiny_cfg

    folder = tmp_path / "run"
    cfg = tiny_cfg(tmp_path)
    save_best(folder, build_model(cfg), {"hparams": build_model(cfg).hparams})
    marker = tmp_path / "pwned"
    _evil_checkpoint(folder / "model.safetensors", marker)
    with pytest.raises(StoreError, match=r"model\.safetensors: not a usable safetensors checkpoint"):
        load_model(folder)
    assert not marker.exists()


@pytest.mark.slow
def test_pickle_training_checkpoint_is_refused_by_the_cli(tmp_path):
    marker = tmp_path / "pwned"
    _evil_checkpoint(tmp_path / "runs" / "isik_spp4" / "last.safetensors", marker)
    proc = cli("train", "--model", "isik", "--spp", "4", "--config", TINY, f"store={tmp_path / 'store'}",
               f"runs={tmp_path / 'runs'}", check=False)
    assert proc.returncode == 2
    assert "last.safetensors: not a checkpoint this trainer wrote" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not marker.exists()


def test_python_object_in_yaml_config_is_refused(tmp_path):
    marker = tmp_path / "pwned"
    cfg = tmp_path / "evil.yaml"
    cfg.write_text(f"seed: !!python/object/apply:os.system ['touch {marker}']\n")
    proc = cli("config", "--config", cfg, check=False)
    assert proc.returncode == 2 and "evil.yaml: not valid YAML" in proc.stderr
    proc = cli("config", f"seed=!!python/object/apply:os.system ['touch {marker}']", check=False)
    assert proc.returncode == 2 and "is not valid YAML" in proc.stderr
    assert not marker.exists()


def _files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


SCENE = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/>{film}</film></sensor>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
</scene>"""


@pytest.mark.parametrize("name", ["../../escaped", "/tmp/escaped", "a/b", "..", "x" * 65])
def test_scene_name_cannot_leave_the_store(tmp_path, name):
    xml = tmp_path / "in" / "box.xml"
    xml.parent.mkdir()
    xml.write_text(SCENE.format(film=""))
    before = _files(tmp_path)
    proc = cli("render-scene", xml, "--store", tmp_path / "a" / "store", "--name", name, "--config", TINY, check=False)
    assert proc.returncode == 2 and "--name" in proc.stderr
    assert _files(tmp_path) == before


def test_film_filename_in_scene_xml_writes_nothing_outside(tmp_path):
    outside = tmp_path / "outside.exr"
    xml = tmp_path / "in" / "box.xml"
    xml.parent.mkdir()
    xml.write_text(SCENE.format(film=f'<string name="filename" value="{outside}"/>'))
    store = tmp_path / "store"
    before = _files(tmp_path)
    # (render-scene takes overrides before the scene file)
    proc = cli("render-scene", "dataset.gt_spp=4", "dataset.stacks=1", xml, "--store", store, "--config", TINY,
               check=False)
    # Mitsuba 3 films have no output file name: the property is refused, with the file named.
    assert proc.returncode == 2 and "box.xml" in proc.stderr and "unreferenced property" in proc.stderr
    assert "Traceback" not in proc.stderr
    new = _files(tmp_path) - before
    assert all(store in p.parents for p in new), sorted(new)
    assert not outside.exists()


@pytest.mark.slow
def test_manifest_scene_ids_cannot_leave_the_store(tmp_path):
    root = tmp_path / "deep" / "store"
    Store(root).write_manifest({"scenes": ["../../../escaped"], "splits": {"train": ["../../../escaped"]}})
    (tmp_path / "escaped").mkdir()
    (tmp_path / "escaped" / "scene.json").write_text(json.dumps({"frames": 1, "gt_spp": 4, "stack_spp": 4, "stacks": 1}))
    with pytest.raises(StoreError, match="scene id '../../../escaped' is not 1-64 letters"):
        Store(root).frames()
    with pytest.raises(StoreError, match="is not 1-64 letters"):
        Store(root).image_path("s0", 0, "../gt1")
    before = _files(tmp_path)
    proc = cli("gt-clean", "--config", TINY, f"store={root}", f"runs={tmp_path / 'runs'}", "clean.epochs=1", check=False)
    assert proc.returncode == 2 and "dataset.json" in proc.stderr and "Traceback" not in proc.stderr
    assert _files(tmp_path) == before
