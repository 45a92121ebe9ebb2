"""Helpers shared by several test modules: the tiny config, the command line in a subprocess, store
comparisons, a synthetic cleaner store, and tiny models. Fixtures live in ``tests/conftest.py``.
torch and the stages load only when a helper that needs them is called."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.store import Store, image_names

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.yaml"
# Not deterministic across runs: wall-clock fields. Everything else must match exactly.
TIMING_KEYS = {"render_seconds", "timing", "reused", "reused_images", "skipped"}
# A small but real cleaner/baseline: a few optimisation steps per epoch on the tiny store.
CLEAN_TINY = ["clean.epochs=5", "clean.batch_size=4", "clean.crop=16", "clean.crops_per_frame=8",
              "clean.channels=[8, 8]", "clean.embed_channels=8", "clean.affinity_channels=4",
              "clean.kernel_size=3", "clean.dilations=[1, 2]", "clean.device=cpu"]


# What the reliability tests found, printed at the end of the run (``tests/conftest.py``):
# reader -> outcome -> count for the fuzz tests; stage -> one line per kill point that ended identical.
FUZZ_TOTALS: dict[str, dict[str, int]] = {}
KILL_POINTS: dict[str, list[str]] = {}


def all_keys() -> list[str]:
    """Every array key of a complete image: each buffer of the schema and its variance."""
    return [k for b in schema.BUFFERS for k in (b.name, schema.variance_name(b.name))]


def cli(*args, check=True, timeout=600):
    proc = subprocess.run([sys.executable, "-m", "pipeline", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}")
    return proc


def train_tiny(model: str, store, runs, *overrides):
    """``train --model MODEL --spp any`` on the tiny config through the command line; the finished process."""
    return cli("train", "--model", model, "--spp", "any", "--config", TINY, f"store={store}", f"runs={runs}",
               *overrides)


def exr_payload(path: Path) -> dict:
    """Pixel data and header record without wall-clock fields."""
    with OpenEXR.File(str(path), separate_channels=True) as f:
        chans = {k: v.pixels.copy() for k, v in f.channels().items()}
        rec = json.loads(f.header()["mcdenoise"])
    return {"channels": chans, "record": {k: v for k, v in rec.items() if k not in TIMING_KEYS}}


def assert_same_store(a: Path, b: Path):
    files_a = sorted(p.relative_to(a) for p in a.rglob("*.exr"))
    files_b = sorted(p.relative_to(b) for p in b.rglob("*.exr"))
    assert files_a == files_b and files_a
    for rel in files_a:
        pa, pb = exr_payload(a / rel), exr_payload(b / rel)
        assert pa["record"] == pb["record"], rel
        assert pa["channels"].keys() == pb["channels"].keys(), rel
        for ch in pa["channels"]:
            np.testing.assert_array_equal(pa["channels"][ch], pb["channels"][ch], err_msg=f"{rel}:{ch}")


# ---- a synthetic store for the cleaner and the baselines (no rendering) ---------------------------
# It mimics what the dataset stage writes (dataset.json, scene.json, frame.json, gt1, gt2 and
# low-spp stacks): a smooth "true" image per frame, GT1/GT2 = truth + independent noise, the
# stacks = truth + stronger noise, every schema buffer present.

SIZE = 16
SCENES = {"s00000": "train", "s00001": "train", "s00002": "val"}
FRAMES = 2
STACKS = 2


def _image(truth: np.ndarray, noise: float, rng: np.random.Generator, spp: int) -> dict[str, np.ndarray]:
    arrays = {}
    for b in schema.BUFFERS:
        if b.name == "color":
            value = np.maximum(truth + noise * rng.standard_normal(truth.shape) * truth, 0)
        elif b.radiance:
            value = 0.2 * truth
        elif b.name == "normal":
            value = np.broadcast_to(np.array([0.0, 0.0, 1.0]), truth.shape)
        elif b.name == "depth":
            value = 1.0 + truth[..., :1]
        else:
            value = np.full(truth.shape[:2] + (b.size,), 0.5)
        arrays[b.name] = value.astype(np.float32)
        var = (noise * truth.mean(axis=2, keepdims=True)) ** 2 if b.name == "color" else np.zeros((1, 1, 1))
        arrays[schema.variance_name(b.name)] = np.broadcast_to(var, value.shape).astype(np.float32)
    return arrays


def make_clean_store(root: Path, seed: int = 0, encoding: str = "compact") -> Path:
    """2 train scenes + 1 val scene × 2 frames × 16² px, images in ``encoding``; returns the store root."""
    store = Store(root)
    rng = np.random.default_rng(seed)
    names = image_names(STACKS)
    splits = {"train": [s for s, k in SCENES.items() if k == "train"], "val": ["s00002"], "test": []}
    store.write_manifest({"config": {}, "scenes": list(SCENES), "splits": splits, "images": names, "packages": {}})
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] / SIZE
    for i, (scene, split) in enumerate(SCENES.items()):
        store.write_scene_manifest(scene, {"scene": scene, "index": i, "split": split, "frames": FRAMES,
                                           "resolution": [SIZE, SIZE], "gt_spp": 64, "stack_spp": 4,
                                           "stacks": STACKS, "images": names})
        for f in range(FRAMES):
            truth = np.stack([0.5 + 0.4 * np.sin(3 * xx + i + f), 0.5 + 0.4 * np.cos(2 * yy + i), 0.3 + 0 * xx], -1)
            records = {}
            for k, name in enumerate(names):
                noise = 0.1 if name.startswith("gt") else 0.5
                records[name] = store.write_image(scene, f, name, _image(truth, noise, rng, 64),
                                                  meta={"image": name, "scene": scene, "frame": f}, encoding=encoding)
            store.write_frame_record(scene, f, {"images": records})
    return root


def tiny_cfg(tmp_path: Path, **clean) -> object:
    overrides = [f"store={tmp_path / 'store'}", f"runs={tmp_path / 'runs'}", "clean.epochs=2",
                 "clean.batch_size=2", "clean.crop=8", "clean.crops_per_frame=2", "clean.channels=[8, 8]",
                 "clean.embed_channels=8", "clean.affinity_channels=4", "clean.kernel_size=3",
                 "clean.dilations=[1, 2]", "clean.device=cpu", "clean.lr=0.01"]
    overrides += [f"clean.{k}={v}" for k, v in clean.items()]
    return load_config(None, overrides)


def save_untrained_isik(folder: Path) -> None:
    """A small untrained Isik network saved as a run folder's best checkpoint."""
    from mcdenoise.clean.data import IN_CHANNELS
    from mcdenoise.clean.model import AffinityDenoiser
    from mcdenoise.clean.train import save_best

    model = AffinityDenoiser(IN_CHANNELS, embed_channels=8, channels=[8, 8], affinity_channels=4, kernel_size=3,
                             dilations=[1, 2])
    save_best(folder, model, {"hparams": model.hparams, "epoch": 0})


def cornell_box(rfilter: str, size: int = 64, spp: int = 4, seed: int = 1) -> np.ndarray:
    """Mitsuba's Cornell box, stock path tracer, with the film's reconstruction filter ``rfilter``: (size, size, 3)."""
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba
    mi = import_mitsuba("llvm_ad_rgb")
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=size, height=size, rfilter={"type": rfilter})
    return np.asarray(mi.render(mi.load_dict(d), spp=spp, seed=seed), np.float32)


def write_rgb_exr(path: Path, rgb: np.ndarray) -> None:
    """An EXR with only R, G and B, as another renderer writes it."""
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION},
                      {c: np.ascontiguousarray(rgb[..., i]) for i, c in enumerate("RGB")}) as f:
        f.write(str(path))


def cornell_box_aux(width: int = 61, height: int = 45, spp: int = 4, seed: int = 1) -> dict[str, np.ndarray]:
    """Mitsuba's Cornell box (box filter, path tracer) with its albedo and shading normal, as a frame's buffers."""
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba
    mi = import_mitsuba("llvm_ad_rgb")
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=width, height=height, rfilter={"type": "box"})
    d["integrator"] = {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal",
                       "integrator": {"type": "path", "max_depth": 8}}
    img = np.asarray(mi.render(mi.load_dict(d), spp=spp, seed=seed), np.float32)
    return {"color": img[..., :3].copy(), "albedo": img[..., 3:6].copy(), "normal": img[..., 6:9].copy()}


# A checkered sphere before a checkered wall under a constant sky, 32x24: a scene to move a camera around
# ({second}: a second sensor, or nothing).
ORBIT_SCENE = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0.5, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film></sensor>
  {second}
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
  <shape type="sphere"><bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
    <transform name="to_uv"><scale x="6" y="6"/></transform></texture></bsdf></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="4"/><translate z="-2"/></transform>
    <bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
      <transform name="to_uv"><scale x="8" y="8"/></transform></texture></bsdf></shape>
</scene>"""


def look_at(origin, target, up) -> np.ndarray:
    """Mitsuba's ``look_at`` as a 4x4 camera_to_world in numpy, so tests build cameras without Mitsuba:
    forward towards ``target``, left = up x forward."""
    origin, target, up = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    forward = target - origin
    forward /= np.linalg.norm(forward)
    left = np.cross(up, forward)
    if np.linalg.norm(left) < 1e-12:
        raise ValueError("look_at: up is parallel to the view direction")
    left /= np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(forward, left), forward, origin
    return m
