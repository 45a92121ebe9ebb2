"""Render one frame (the unit of work) into the store: GT1, GT2 and the low-spp stacks.

Runs inside a worker process (local executor) or a Ray task. The scene of the previous task is
kept while consecutive tasks belong to the same scene, so only the camera changes between
frames; drjit reuses its compiled kernel as long as the previous scene was freed first,
hence the explicit ``del`` + ``gc.collect()`` before building another one.

Images already on disk are kept (writes are atomic, so an existing file is complete): a frame
interrupted half-way resumes at the first missing image, and the same seeds make the resumed
frame identical to an uninterrupted one.
"""
from __future__ import annotations

import gc
import time
from dataclasses import dataclass, field

import numpy as np

from pipeline import schema
from pipeline.exr import StoreError
from pipeline.mitsuba_env import import_mitsuba
from pipeline.store import Store, image_names, sha256


@dataclass
class FrameTask:
    store: str
    scene: str            # scene id in the store
    frame: int
    desc: dict            # scene description (render.scene); for external scenes {"xml": path}
    resolution: tuple | None  # (width, height); None: the external scene's own film size
    gt_spp: int
    stack_spp: int
    stacks: int
    seeds: dict           # image name -> seed
    render: dict          # RenderConfig as a dict
    images: list = field(default_factory=list)  # subset to render; empty = all


_CACHE: dict = {"scene_id": None, "scene": None, "features": None, "sensors": {}}


def _scene(mi, task: FrameTask):
    """The Mitsuba scene of ``task``, reusing the previous one when it is the same scene."""
    from render.buffers import needed_features

    if _CACHE["scene_id"] == task.scene:
        return _CACHE["scene"], _CACHE["features"], 0.0
    _CACHE.update(scene_id=None, scene=None, features=None)
    gc.collect()
    t0 = time.perf_counter()
    if "xml" in task.desc:
        from render.external import load_external_scene
        scene = load_external_scene(mi, task.desc["xml"])
    else:
        from render.scene import build_scene
        scene = build_scene(mi, task.desc)
    if task.render["features"] == "all":
        features = set(schema.OPTIONAL_FEATURES)
    else:
        features = needed_features(mi, scene)
    _CACHE.update(scene_id=task.scene, scene=scene, features=features)
    return scene, features, time.perf_counter() - t0


def _sensor(mi, task: FrameTask, scene):
    w, h = task.resolution or (None, None)
    if "xml" in task.desc:
        from render.external import external_sensor
        return external_sensor(mi, scene, w, h)
    from render.scene import build_sensor
    return build_sensor(mi, task.desc, task.frame, w, h)


def render_frame(task: FrameTask) -> dict:
    """Render the missing images of one frame, then write its ``frame.json``. Returns it."""
    from render.buffers import render_image

    t_start = time.perf_counter()
    store = Store(task.store)
    names = task.images or image_names(task.stacks)
    existing = store.frame_record(task.scene, task.frame) if not task.images else None
    if existing and all(n in existing.get("images", {}) and store.image_path(task.scene, task.frame, n).exists()
                        for n in names):
        return {**existing, "skipped": True}
    # A SIGKILL during a write leaves its temporary file (never a partial image): drop them.
    # Only the task of this frame writes into this folder, so nothing live is removed.
    frame_dir = store.frame_dir(task.scene, task.frame)
    for tmp in frame_dir.glob(".*.tmp") if frame_dir.exists() else ():
        tmp.unlink(missing_ok=True)
    mi = import_mitsuba(task.render["variant"], task.render["threads"])
    scene, features, build_s = _scene(mi, task)
    t0 = time.perf_counter()
    sensor = _sensor(mi, task, scene)
    build_s += time.perf_counter() - t0

    records: dict[str, dict] = {}
    render_s = write_s = 0.0
    reused = 0
    for name in names:
        path = store.image_path(task.scene, task.frame, name)
        if path.exists():
            try:
                header = store.image_header(task.scene, task.frame, name)
                records[name] = {**header, "bytes": path.stat().st_size, "sha256": sha256(path), "reused": True}
                reused += 1
                continue
            except StoreError:
                path.unlink()  # unreadable leftover (e.g. written by an older version): render again
        spp = task.gt_spp if name.startswith("gt") else task.stack_spp
        result = render_image(mi, scene, sensor, spp=spp, seed=task.seeds[name], features=features,
                              max_depth=task.render["max_depth"], rr_depth=task.render["rr_depth"])
        render_s += result.seconds
        t0 = time.perf_counter()
        meta = {"image": name, "spp": spp, "seed": task.seeds[name], "scene": task.scene, "frame": task.frame,
                "render_seconds": round(result.seconds, 4), "nonfinite": result.nonfinite,
                "features": sorted(features)}
        records[name] = store.write_image(task.scene, task.frame, name, result.buffers, result.constants,
                                          meta, omit_constant=task.render["omit_constant"],
                                          encoding=task.render.get("encoding", "compact"))
        write_s += time.perf_counter() - t0
    w, h = (int(v) for v in sensor.film().size())
    record = {
        "scene": task.scene, "frame": task.frame, "width": w, "height": h,
        "images": records, "features": sorted(features),
        "samples": int(w * h * sum(r["spp"] for r in records.values())),
        "nonfinite": sum(sum(r.get("nonfinite", {}).values()) for r in records.values()),
        "bytes": sum(r["bytes"] for r in records.values()),
        "timing": {"build": round(build_s, 4), "render": round(render_s, 4), "write": round(write_s, 4),
                   "total": round(time.perf_counter() - t_start, 4)},
        "reused_images": reused,
        # The camera frame (columns: left, up, forward, origin): lets consumers turn the
        # world-space normals into camera space (train.data).
        "camera_to_world": np.round(np.asarray(sensor.world_transform().matrix.numpy(), np.float64)
                                    .reshape(4, 4), 6).tolist(),
    }
    if not task.images:
        store.write_frame_record(task.scene, task.frame, record)
    return record
