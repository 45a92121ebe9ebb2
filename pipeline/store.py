"""The on-disk EXR buffer store: the one reader/writer API every stage uses.

Layout (documented for users in ``docs/store.md``)::

    STORE/dataset.json                       dataset manifest: config, scenes, split by scene
    STORE/scenes/<scene>/scene.json          scene manifest: description, seeds, settings, versions
    STORE/scenes/<scene>/<frame>/gt1.exr     ground truth 1 (gt_spp), every buffer + variance
    STORE/scenes/<scene>/<frame>/gt2.exr     ground truth 2, independent seed
    STORE/scenes/<scene>/<frame>/s00.exr ..  K low-spp stacks (stack_spp each)
    STORE/scenes/<scene>/<frame>/frame.json  written last: marks the frame complete, per-image records

Every file is written to a temporary name and renamed, so a file that exists is complete.
"""
from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import schema
from .exr import StoreError, atomic_write_json, read_header, read_image, read_json, write_image

STORE_FORMAT = "mcdenoise-store"
STORE_VERSION = 1
GT_IMAGES = ("gt1", "gt2")
# Scene ids and image names become path components: nothing that could leave the store.
NAME_RE = re.compile(r"[A-Za-z0-9_-]{1,64}")
MAX_FRAMES = 1 << 20


def stack_name(k: int) -> str:
    return f"s{k:02d}"


def frame_name(frame: int) -> str:
    return f"{frame:03d}"


def image_names(stacks: int) -> list[str]:
    """Images of a frame in render order: GT1, GT2, then the stacks."""
    return list(GT_IMAGES) + [stack_name(k) for k in range(stacks)]


def image_seed(master: int, scene_index: int, frame: int, image: int, frames: int, images: int) -> int:
    """A distinct 32-bit seed per image of the dataset.

    A counter, not a hash: the (scene, frame, image) triples enumerate distinct integers, so no
    two images of one dataset share a seed (up to 2^32 images). The master seed only offsets it.
    Mitsuba hashes the seed with the sample index, so consecutive seeds are independent streams.
    """
    counter = (scene_index * frames + frame) * images + image
    return int((master * 2654435761 + counter) % (1 << 32))


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def poolable(spp: int, stack_spp: int, stacks: int) -> bool:
    """Whether ``spp`` samples per pixel can be pooled from ``stacks`` stacks of ``stack_spp`` each:
    a multiple of ``stack_spp``, from one stack up to all of them."""
    return spp % stack_spp == 0 and 1 <= spp // stack_spp <= stacks


def combine_stacks(images: list[dict[str, np.ndarray]], spp_each) -> dict[str, np.ndarray]:
    """Average K independent stacks, with the exact pooled variance.

    ``spp_each``: the samples of every stack (an int) or one count per stack (a list; the
    progressive ground truth pools its running estimate with each new pass this way).
    Stack k gives a mean m_k of n_k samples and the variance of that mean v_k = s_k²/n_k. The
    result equals what one render with N = Σ n_k samples reports: mean m = Σ n_k·m_k / N and
    variance of the mean s²/N with the pooled sample variance
        s² = [ Σ_k (n_k−1)·n_k·v_k + Σ_k n_k·(m_k − m)² ] / (N − 1),
    i.e. within-stack and between-stack scatter together (tests/test_store.py checks this
    against the variance computed from the pooled samples directly).
    """
    if not images:
        raise ValueError("combine_stacks needs at least one stack")
    if len(images) == 1:
        return {k: v.copy() for k, v in images[0].items()}
    counts = [int(spp_each)] * len(images) if np.isscalar(spp_each) else [int(c) for c in spp_each]
    if len(counts) != len(images):
        raise ValueError(f"combine_stacks: {len(images)} stacks but {len(counts)} sample counts")
    N = float(sum(counts))
    out: dict[str, np.ndarray] = {}
    names = [k for k in images[0] if not k.endswith(".variance")]
    for name in names:
        means = np.stack([img[name].astype(np.float64) for img in images])
        n = np.array(counts, dtype=np.float64).reshape((-1,) + (1,) * (means.ndim - 1))
        m = (n * means).sum(axis=0) / N
        out[name] = m.astype(np.float32)
        vkey = schema.variance_name(name)
        if vkey in images[0]:
            within = sum(c * (c - 1) * img[vkey].astype(np.float64) for c, img in zip(counts, images))
            between = (n * (means - m) ** 2).sum(axis=0)
            s2 = (within + between) / (N - 1)
            out[vkey] = (s2 / N).astype(np.float32)
    return out


@dataclass(frozen=True)
class FrameKey:
    scene: str
    frame: int

    def __str__(self) -> str:
        return f"{self.scene}/{frame_name(self.frame)}"

    def previous(self) -> FrameKey | None:
        """The frame before this one on its scene's camera move: frame − 1, the one rendered just before, whether
        or not it is among the frames at hand (a frame before a gap has no previous frame there); None for 0."""
        return FrameKey(self.scene, self.frame - 1) if self.frame > 0 else None


class Store:
    """Reader/writer for one store directory."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    # ---- paths -------------------------------------------------------------------------
    @property
    def manifest_path(self) -> Path:
        return self.root / "dataset.json"

    def scene_dir(self, scene: str) -> Path:
        return self.root / "scenes" / _name(scene, self.root, "scene id")

    def frame_dir(self, scene: str, frame: int) -> Path:
        return self.scene_dir(scene) / frame_name(frame)

    def image_path(self, scene: str, frame: int, image: str) -> Path:
        return self.frame_dir(scene, frame) / f"{_name(image, self.root, 'image name')}.exr"

    # ---- manifests ---------------------------------------------------------------------
    def manifest(self) -> dict:
        path = self.manifest_path
        data = read_json(path, "dataset manifest")
        if data.get("format") != STORE_FORMAT:
            raise StoreError(f"{path}: not a {STORE_FORMAT} manifest")
        if data.get("version") != STORE_VERSION:
            raise StoreError(f"{path}: store version {data.get('version')!r}, this code reads {STORE_VERSION}")
        for key in ("scenes", "splits"):
            if key not in data:
                raise StoreError(f"{path}: key {key!r} is missing")
        _names(data["scenes"], path, "scenes", "scene id")
        if not isinstance(data["splits"], dict):
            raise StoreError(f"{path}: key 'splits' must map split names to lists of scene ids")
        for split, ids in data["splits"].items():
            _names(ids, path, f"splits.{split}", "scene id")
        return data

    def write_manifest(self, data: dict) -> None:
        atomic_write_json(self.manifest_path, {"format": STORE_FORMAT, "version": STORE_VERSION, **data})

    def scene_manifest(self, scene: str) -> dict:
        path = self.scene_dir(scene) / "scene.json"
        data = read_json(path, "scene manifest")
        for key in ("frames", "gt_spp", "stack_spp", "stacks"):
            _count(data, key, path, MAX_FRAMES if key == "frames" else 1 << 24)
        if "images" in data:
            _names(data["images"], path, "images", "image name")
        res = data.get("resolution")
        if res is not None and not (isinstance(res, list) and len(res) == 2
                                    and all(type(v) is int and 0 < v <= 1 << 14 for v in res)):
            raise StoreError(f"{path}: key 'resolution' must be [width, height] or null, got {res!r}")
        return data

    def write_scene_manifest(self, scene: str, data: dict) -> None:
        atomic_write_json(self.scene_dir(scene) / "scene.json", data)

    def frame_record(self, scene: str, frame: int) -> dict | None:
        path = self.frame_dir(scene, frame) / "frame.json"
        if not path.exists():
            return None
        data = read_json(path, "frame record")
        images = data.get("images")
        if not isinstance(images, dict) or not all(isinstance(v, dict) for v in images.values()):
            raise StoreError(f"{path}: key 'images' must map image names to records")
        _names(list(images), path, "images", "image name")
        return data

    def camera(self, scene: str, frame: int):
        """The frame's ``pipeline.motion.Camera`` from its ``frame.json``; StoreError in one line naming the
        file and what is missing (no record yet, or a frame rendered before cameras were recorded). A
        generated scene's frame rendered before its field of view was recorded takes it from the scene's
        description (``render.camera`` writes every frame's pose and fov there)."""
        from .motion import camera_from_record
        path = self.frame_dir(scene, frame) / "frame.json"
        record = self.frame_record(scene, frame)
        if record is None:
            raise StoreError(f"{path}: frame record is missing: the frame is not rendered, so it has no camera")
        if "fov_x" not in record:
            described = self.scene_manifest(scene).get("description", {}).get("camera", {}).get("frames", [])
            if frame < len(described) and "fov" in described[frame]:
                record = {**record, "fov_x": described[frame]["fov"]}
        return camera_from_record(record, str(path))

    def write_frame_record(self, scene: str, frame: int, data: dict) -> None:
        atomic_write_json(self.frame_dir(scene, frame) / "frame.json", data)

    # ---- frames ------------------------------------------------------------------------
    def scenes(self, split: str | None = None) -> list[str]:
        m = self.manifest()
        if split is None:
            return list(m["scenes"])
        if split not in m["splits"]:
            raise StoreError(f"{self.manifest_path}: no split {split!r} (have {', '.join(m['splits'])})")
        return list(m["splits"][split])

    def frames(self, split: str | None = None) -> list[FrameKey]:
        out = []
        for scene in self.scenes(split):
            sm = self.scene_manifest(scene)
            out += [FrameKey(scene, f) for f in range(int(sm["frames"]))]
        return out

    def frames_with(self, split: str, images: tuple[str, ...] | list[str] = ("gt_clean",)) -> list[FrameKey]:
        """The frames of ``split`` with every image of ``images`` on disk (by default ``gt_clean``: the frames
        a denoiser trains and is scored on); none for a split this store does not have."""
        if split not in self.manifest()["splits"]:
            return []
        return [k for k in self.frames(split) if all(self.image_path(k.scene, k.frame, n).exists() for n in images)]

    def training_frames(self) -> tuple[list[FrameKey], list[FrameKey]]:
        """(train, val) frames with gt_clean, what a denoiser trains and validates on; StoreError naming the
        store and what to run when it has no dataset or no train frame with gt_clean."""
        if not self.manifest_path.exists():
            raise StoreError(f"{self.root}: no dataset; run `make dataset` first")
        train = self.frames_with("train")
        if not train:
            raise StoreError(f"{self.root}: no training frame with gt_clean; run `make gt-clean`")
        return train, self.frames_with("val")

    def is_frame_complete(self, scene: str, frame: int, images: list[str]) -> bool:
        """True when frame.json lists every expected image and each file is on disk."""
        try:
            rec = self.frame_record(scene, frame)
        except StoreError:
            return False
        if rec is None:
            return False
        have = rec.get("images", {})
        return all(name in have and self.image_path(scene, frame, name).exists() for name in images)

    def spp_choices(self, spp) -> list[int]:
        """Sample counts a model for ``spp`` trains on: ``[spp]``, or for 'any' every power-of-two
        multiple of the stack spp the stacks can pool (4, 8, 16, 32, 64 for 16 stacks of 4 spp)."""
        sm = self.scene_manifest(self.scenes()[0])
        n, k = int(sm["stack_spp"]), int(sm["stacks"])
        if str(spp) == "any":
            return [n * 2 ** i for i in range(k.bit_length())]
        spp = int(spp)
        if not poolable(spp, n, k):
            raise StoreError(f"{self.root}: spp {spp} is not a multiple of the stack spp {n} up to {n * k}")
        return [spp]

    # ---- images ------------------------------------------------------------------------
    def write_image(self, scene: str, frame: int, image: str, arrays, constants=None, meta=None,
                    omit_constant: bool = True, encoding: str = "compact", camera=None) -> dict:
        """Write one image (``pipeline.exr.write_image``; a store's images are compact unless the
        config's ``render.encoding`` says 'exact'; ``camera``, the frame's, goes into its header);
        its record plus ``bytes`` and ``sha256``."""
        path = self.image_path(scene, frame, image)
        record = write_image(path, arrays, constants, meta, omit_constant, encoding=encoding, camera=camera)
        return {**record, "bytes": path.stat().st_size, "sha256": sha256(path)}

    def read_image(self, scene: str, frame: int, image: str, buffers: list[str] | None = None):
        return read_image(self.image_path(scene, frame, image), buffers)

    def image_header(self, scene: str, frame: int, image: str) -> dict:
        return read_header(self.image_path(scene, frame, image))

    def read(self, scene: str, frame: int, spp: int, buffers: list[str] | None = None,
             stacks: list[int] | None = None, rng: np.random.Generator | None = None) -> dict[str, np.ndarray]:
        """Buffers of (scene, frame) at ``spp`` samples: the average of spp/stack_spp stacks.

        Which stacks: ``stacks`` if given, else a random choice from ``rng`` (as the paper's
        training does), else the first ones. ``spp`` equal to the GT sample count reads GT1.
        """
        sm = self.scene_manifest(scene)
        n, total = int(sm["stack_spp"]), int(sm["stacks"])
        if spp == int(sm["gt_spp"]) and stacks is None:
            return self.read_image(scene, frame, "gt1", buffers)[0]
        if not poolable(spp, n, total):
            raise StoreError(f"{self.scene_dir(scene)}: spp {spp} is not a multiple of the stack spp {n} "
                             f"between {n} and {n * total} (or the GT spp {sm['gt_spp']})")
        k = spp // n
        if stacks is None:
            stacks = sorted(rng.choice(total, size=k, replace=False).tolist()) if rng is not None else list(range(k))
        if len(stacks) != k:
            raise StoreError(f"spp {spp} needs {k} stacks, got {len(stacks)}")
        images = [self.read_image(scene, frame, stack_name(i), buffers)[0] for i in stacks]
        return combine_stacks(images, n)


def _name(value, path: Path, what: str) -> str:
    if not isinstance(value, str) or not NAME_RE.fullmatch(value):
        raise StoreError(f"{path}: {what} {value!r} is not 1-64 letters, digits, '_' or '-'")
    return value


def _names(values, path: Path, key: str, what: str) -> list:
    if not isinstance(values, list):
        raise StoreError(f"{path}: key {key!r} must be a list of {what}s, got {type(values).__name__}")
    for v in values:
        _name(v, path, f"{key}: {what}")
    return values


def _count(data: dict, key: str, path: Path, top: int) -> int:
    value = data.get(key)
    if type(value) is not int or not 1 <= value <= top:
        raise StoreError(f"{path}: key {key!r} must be an integer in 1..{top}, got {value!r}")
    return value
