"""The GPU recipe (tools/gpu/recipe.py, a tool of the checkout, not of the installed package): what it carries,
its command line, and the whole recipe on the CPU in seconds."""
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mcdenoise.pipeline.errors import TrainError

ROOT = Path(__file__).resolve().parent.parent
RECIPE = ROOT / "tools" / "gpu" / "recipe.py"


def _load_recipe():
    """tools/gpu/recipe.py as a module (tools/ is no package); registered first, as its dataclass needs."""
    spec = importlib.util.spec_from_file_location("gpu_recipe", RECIPE)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


gpu_recipe = _load_recipe()


def recipe(*args, **kw) -> subprocess.CompletedProcess:
    """``python tools/gpu/recipe.py ARGS`` from the repository root."""
    return subprocess.run([sys.executable, str(RECIPE.relative_to(ROOT)), *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, **kw)


def test_the_carried_packages_are_what_the_gpu_image_lacks():
    """Every carried package is pinned as requirements.lock pins it and none is in the image's list (a
    second copy of an image package broke the image's own once: huggingface_hub beside peft)."""
    pins = gpu_recipe.check_carried()
    locked = gpu_recipe.locked_versions()
    assert [p.split("==")[0] for p in pins] == list(gpu_recipe.CARRIED)
    assert all(locked[gpu_recipe.normalise(p.split("==")[0])] == p.split("==")[1] for p in pins)
    image = gpu_recipe.image_packages()
    assert {"torch", "numpy", "safetensors", "huggingface-hub", "peft", "pyyaml", "tqdm", "scipy"} <= image
    assert not image & {gpu_recipe.normalise(n) for n in gpu_recipe.CARRIED}
    with pytest.raises(TrainError, match="already has huggingface_hub"):
        gpu_recipe.check_carried(("diffusers", "huggingface_hub"))


def test_mitsuba_is_cut_to_the_variants_and_plugins_the_renderer_uses():
    keep = gpu_recipe.keep_member
    assert keep("mitsuba/cuda_ad_rgb.cpython-312-x86_64-linux-gnu.so")
    assert keep("mitsuba/scalar_rgb.cpython-312-x86_64-linux-gnu.so")
    assert not keep("mitsuba/llvm_ad_rgb.cpython-312-x86_64-linux-gnu.so")
    assert not keep("mitsuba/cuda_ad_spectral.cpython-312-x86_64-linux-gnu.so")
    assert not keep("mitsuba/scalar_spectral.cpython-312-x86_64-linux-gnu.so")
    assert not keep("mitsuba/data/srgb.coeff") and not keep("mitsuba/data/sunsky/sunsky_datasets.bin")
    assert not keep("mitsuba/plugins/volpath.so") and not keep("mitsuba/include/mitsuba/core/fwd.h")
    for plugin in ("path", "principled", "roughdielectric", "area", "envmap", "hdrfilm", "box", "moment", "aov"):
        assert keep(f"mitsuba/plugins/{plugin}.so")
    assert keep("mitsuba/libmitsuba.so") and keep("mitsuba/python/util.py")
    assert keep("diffusers/schedulers/scheduling_ddim.py") and not keep("diffusers/__pycache__/x.pyc")
    assert not keep("drjit/__init__.pyi")


def test_the_aux_networks_travel_as_tza_files(tmp_path):
    """prepare --no-wheels writes OIDN's aux networks (pyoidn does not travel) and carried.json."""
    record = gpu_recipe.prepare(tmp_path / "gpu", wheels=False)
    assert set(record["files"]) == {"oidn/rt_alb_large.tza", "oidn/rt_nrm_large.tza"}
    assert json.loads((tmp_path / "gpu" / "carried.json").read_text())["packages"] == gpu_recipe.check_carried()
    assert all((tmp_path / "gpu" / f).stat().st_size == n for f, n in record["files"].items())


@pytest.mark.slow
def test_the_whole_recipe_runs_on_the_cpu(tmp_path):
    """``DEVICE=cpu CONFIG=configs/tiny.yaml MINUTES=0.2 bash tools/gpu/recipe.sh``: every phase runs, the files
    that come back are there (a model folder denoise loads, at most 8 files), the curve starts at the model it
    trained on."""
    out, work = tmp_path / "out", tmp_path / "work"
    env = {**os.environ, "DEVICE": "cpu", "CONFIG": "configs/tiny.yaml", "MINUTES": "0.2", "OUT": str(out),
           "WORK": str(work), "PYTHON": sys.executable}
    proc = subprocess.run(["bash", "tools/gpu/recipe.sh", "--batch", "2", "--loader-workers", "1", "--workers", "1"],
                          cwd=ROOT, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    files = {p.name for p in out.iterdir()}
    assert {"control.safetensors", "base.tza", "model.json", "report.md", "result.json", "logs.txt"} <= files
    assert len(files) <= 8 and files <= {"control.safetensors", "base.tza", "model.json", "report.md", "result.json",
                                         "logs.txt", "loss.png", "snapshots.safetensors"}
    r = json.loads((out / "result.json").read_text())
    assert list(r["phases"]) == ["render_val", "render", "clean", "train", "bench"]
    render = r["phases"]["render"]
    assert render["splits"]["val"] >= 1 and render["splits"]["train"] >= 1 and render["splits"]["test"] == 0
    curve = r["phases"]["train"]["curve"]
    assert curve[0]["epoch"] == 0 and curve[0]["mpix"] == 0 and len(curve) >= 2 and curve[-1]["mpix"] > 0
    row = r["bench"]["rows"][0]
    assert row["size"] == "64x64" and r["bench"]["precision"] == "fp32"
    assert all(row[k] > 0 for k in ("ours_1step_s", "ours_3step_s", "base_s", "ours_network_s", "base_network_s"))
    # what comes back is a model folder that loads: the shipped base beside the trained Control Module
    from mcdenoise.train.model import load
    model, meta = load(out)
    assert meta["base_network"] == "rt_hdr_calb_cnrm_large" and next(model.control.parameters()).dtype == torch.float32
    assert "# GPU recipe on CPU only" in (out / "report.md").read_text()
    # the kept epochs come back too (here the one epoch the dry run trains), and unpack as model folders that load
    assert r["phases"]["train"]["snapshots"] == [{"epoch": 1, "mpix": curve[1]["mpix"], "val_psnr": curve[1]["val_psnr"]}]
    dest = tmp_path / "candidate"
    proc = recipe("unpack", out, dest)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split() == [str(dest), str(dest / "epoch1")]
    kept, kept_meta = load(work / "runs" / "diffusion_sppany_gpu" / "epoch1")
    snap, snap_meta = load(dest / "epoch1")
    assert snap_meta == kept_meta and snap_meta["epoch"] == 1
    for (name, a), b in zip(kept.control.state_dict().items(), snap.control.state_dict().values()):
        assert torch.equal(a.half().float(), b), name    # float16 on the way back, exactly that rounding
    assert torch.equal(next(load(dest)[0].control.parameters()), next(model.control.parameters()))


def test_snapshots_spread_over_the_kept_epochs():
    assert gpu_recipe.spread([], 6) == []
    assert gpu_recipe.spread([1, 2, 4], 6) == [1, 2, 4]
    kept = [2 ** i for i in range(8)]    # 1 .. 128: a run of 128 to 255 epochs
    assert gpu_recipe.spread(kept, 6) == [1, 2, 8, 16, 64, 128]
    assert all(gpu_recipe.spread(kept[:n], 6)[-1] == kept[n - 1] for n in range(1, 9))
    assert set(gpu_recipe.KEEP_EPOCHS[:8]) == set(kept)


def test_the_command_line_and_its_help(tmp_path):
    """``--help`` of the tool and of each command exits 0, every option has help text; a PipelineError is one line
    on stderr and exit status 2, as in ``python -m pipeline``."""
    proc = recipe("--help")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: python tools/gpu/recipe.py") and all(
        c in proc.stdout for c in ("prepare", "run", "unpack"))
    for command in ("prepare", "run", "unpack"):
        proc = recipe(command, "--help")
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.startswith(f"usage: python tools/gpu/recipe.py {command}")
    parser = gpu_recipe.build_parser()
    (sub,) = [a for a in parser._actions if a.dest == "command"]
    assert set(sub.choices) == {"prepare", "run", "unpack"}
    for name, p in sub.choices.items():
        assert p.description and "\n" not in p.description, name
        for action in p._actions:
            assert action.help, f"{name} {action.dest}"
    args = parser.parse_args(["run", "--out", "o"])
    assert (args.config, args.minutes, args.device, args.batch, args.crop, args.work) == (
        "configs/ship.yaml", 9.0, "auto", 64, 128, "/tmp/mcdenoise_gpu")
    proc = recipe("unpack", tmp_path / "no such run", tmp_path / "dest")
    assert proc.returncode == 2 and proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1, proc.stderr


def test_the_installed_package_has_no_gpu_files():
    """The recipe lives in tools/gpu/, outside every folder pyproject.toml installs, and nothing of it is package
    data."""
    tomllib = pytest.importorskip("tomllib")
    setup = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert not any("gpu" in pattern for patterns in setup.get("package-data", {}).values() for pattern in patterns)
    assert not any(d.split("/")[0] == "tools" for d in setup["package-dir"].values())
    assert not any(p.startswith("tools") for p in setup["packages"])
    for folder in setup["package-dir"].values():
        assert not [p for p in (ROOT / folder).rglob("*gpu*") if "__pycache__" not in p.parts], folder
    assert not list((ROOT / "train").glob("gpu_*"))
    assert {p.name for p in RECIPE.parent.iterdir() if p.is_file()} >= {"recipe.py", "recipe.sh", "image.txt"}
