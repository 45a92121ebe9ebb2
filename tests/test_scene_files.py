"""The hand-made scenes of configs/scenes: every XML loads, every validation scene (``val_*``) carries its short
camera move as exactly two perspective sensors (start pose first, end pose second) with the same field of view and
the same 128 x 128 box-filtered film, render-scene's camera is the first sensor, and the README lists every
validation scene (table row and the validation ``make eval`` command)."""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "configs" / "scenes"
ALL = sorted(SCENES.glob("*.xml"))
VAL = sorted(SCENES.glob("val_*.xml"))

BUILTIN_SHAPES = {"rectangle", "cube", "sphere", "cylinder", "disk"}
BUILTIN_EMITTERS = {"area", "spot", "point", "constant", "directional", "envmap"}


def vec(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.split(",")])


def sensors(path: Path) -> list[ET.Element]:
    return ET.parse(path).getroot().findall("sensor")


def test_there_are_at_least_twenty_validation_scenes():
    assert len(VAL) >= 20, [p.name for p in VAL]


@pytest.mark.parametrize("path", ALL, ids=lambda p: p.stem)
def test_scene_is_built_from_builtins_with_no_integrator(path):
    root = ET.parse(path).getroot()
    assert root.find("integrator") is None
    assert {s.get("type") for s in root.iter("shape")} <= BUILTIN_SHAPES
    assert {e.get("type") for e in root.iter("emitter")} <= BUILTIN_EMITTERS


@pytest.mark.parametrize("path", VAL, ids=lambda p: p.stem)
def test_validation_scene_has_two_sensors_with_the_same_fov_and_film(path):
    cams = sensors(path)
    assert len(cams) == 2, f"{path.name}: {len(cams)} sensors (want start and end pose of the camera move)"
    for cam in cams:
        assert cam.get("type") == "perspective"
        film = cam.find("film")
        assert film.get("type") == "hdrfilm"
        size = {i.get("name"): int(i.get("value")) for i in film.findall("integer")}
        assert size == {"width": 128, "height": 128}
        assert film.find("rfilter").get("type") == "box"
    fovs = [cam.find("float[@name='fov']").get("value") for cam in cams]
    assert fovs[0] == fovs[1]
    films = [ET.tostring(cam.find("film")) for cam in cams]
    assert films[0] == films[1]
    (a, b) = [cam.find("transform/lookat") for cam in cams]
    assert a.get("up") == b.get("up")
    moved = np.linalg.norm(vec(a.get("origin")) - vec(b.get("origin")))
    turned = vec(a.get("target")) - vec(a.get("origin")), vec(b.get("target")) - vec(b.get("origin"))
    cos = float(np.dot(*turned) / np.linalg.norm(turned[0]) / np.linalg.norm(turned[1]))
    assert moved > 0.05 or cos < np.cos(np.radians(3)), f"{path.name}: the end pose hardly differs from the start"
    assert moved <= 0.55 and cos > np.cos(np.radians(35)), f"{path.name}: a move of {moved:.2f} m is not a short one"


def test_readme_lists_every_validation_scene():
    readme = (SCENES / "README.md").read_text()
    command = re.search(r"# the validation set.*?\n(make eval SCENES=\"[^\"]*\")", readme, re.S)
    assert command, "README: the validation make eval command is missing"
    for path in VAL:
        assert f"| `{path.name}` |" in readme, f"README: no table row for {path.name}"
        assert f"configs/scenes/{path.name}" in command.group(1), f"README: {path.name} not in the validation command"


# Loads every scene in a fresh process, as render-scene does (its frames render in worker processes): Mitsuba's
# own OpenEXR thread pool, which reads metal_dome's texture, can deadlock in a process whose earlier tests
# used other EXR and OIDN threads.
_LOAD = """
import json, sys
import numpy as np
from mcdenoise.pipeline.mitsuba_env import import_mitsuba
from mcdenoise.render.frame import external_sensor, load_external_scene
mi = import_mitsuba("llvm_ad_rgb")
out = {}
for path in sys.argv[1:]:
    scene = load_external_scene(mi, path)
    mats = [np.asarray(mi.traverse(c)["to_world"].matrix.numpy()).reshape(4, 4).tolist() for c in scene.sensors()]
    ours = external_sensor(mi, scene, None, None)
    out[path] = {"sensors": mats, "ours": np.asarray(mi.traverse(ours)["to_world"].matrix.numpy()).reshape(4, 4).tolist(),
                 "film": list(ours.film().size())}
print(json.dumps(out))
"""


@pytest.mark.slow
def test_every_scene_loads_and_render_scene_uses_the_first_sensor():
    import json
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", _LOAD, *map(str, ALL)], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    loaded = json.loads(proc.stdout.strip().splitlines()[-1])
    for path in ALL:
        got = loaded[str(path)]
        cams = [np.asarray(m) for m in got["sensors"]]
        assert len(cams) == len(sensors(path)), path.name
        if not path.name.startswith("val_"):
            continue
        start, end = cams
        origin = vec(sensors(path)[0].find("transform/lookat").get("origin"))
        assert np.allclose(start[:3, 3], origin, atol=1e-4), f"{path.name}: scene.sensors()[0] is not the first sensor"
        assert not np.allclose(start, end), path.name
        matrix = np.asarray(got["ours"])
        assert np.allclose(matrix[:3, 3], origin, atol=1e-4), f"{path.name}: render-scene does not render the start pose"
        assert tuple(got["film"]) == (128, 128)
