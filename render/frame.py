"""Render one frame (the unit of work) into the store: GT1, GT2 and the low-spp stacks.

Runs inside a worker process (local executor) or a Ray task. The scene of the previous task is
kept while consecutive tasks belong to the same scene, so only the camera changes between
frames; drjit reuses its compiled kernel as long as the previous scene was freed first,
hence the explicit ``del`` + ``gc.collect()`` before building another one.

A frame's scene is a random scene's description (built by ``render.scene``) or a user's Mitsuba
XML (``{"xml": path}``, from ``render.external``): ``load_external_scene`` loads it as it is and
``external_sensor`` puts our film on its first camera.

Images already on disk are kept (writes are atomic, so an existing file is complete): a frame
interrupted half-way resumes at the first missing image, and the same seeds make the resumed
frame identical to an uninterrupted one.
"""
from __future__ import annotations

import gc
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcdenoise.pipeline import metrics, schema
from mcdenoise.pipeline.errors import PipelineError, innermost_message
from mcdenoise.pipeline.exr import StoreError
from mcdenoise.pipeline.mitsuba_env import import_mitsuba
from mcdenoise.pipeline.motion import Camera, camera_record
from mcdenoise.pipeline.store import GT_IMAGES, Store, image_names, sha256


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
    gt_target_psnr: float | None = None  # progressive GT: see render.progressive; None = gt_spp in one render
    gt_pass_spp: int = 0                 # spp per pass of a progressive GT (gt_spp is then its cap)


class ExternalSceneError(PipelineError, RuntimeError):
    """A Mitsuba scene file from the user cannot be rendered; the message names the file or what is missing."""


class RenderFailed(RuntimeError):
    """Mitsuba failed inside a render of a random scene; the message carries Mitsuba's own reason."""


def load_external_scene(mi, xml: str, defines: dict[str, str] | None = None):
    """The scene of ``xml`` with its ``$name`` parameters set from ``defines`` (``-D name=value``, as
    Mitsuba's own command line; parameters the XML declares with ``<default>`` may be left out)."""
    path = Path(xml)
    if not path.is_file():
        raise ExternalSceneError(f"{xml}: scene file not found")
    try:
        # Mitsuba resolves relative asset paths against the XML's folder.
        return mi.load_file(str(path.resolve()), parallel=False, optimize=False,  # fixed order: see render.scene
                            **(defines or {}))
    except Exception as exc:  # Mitsuba raises RuntimeError with the parser's message
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        first = re.sub(r"^\[[^]]*\] ", "", first)   # Mitsuba's source location ([parser.cpp:451])
        missing = re.search(r"undefined parameter: \$(\w+)", first)
        how = (f"; give it a value with -D {missing.group(1)}=VALUE (make eval: DEFINES=\"{missing.group(1)}=VALUE\")"
               if missing else "")
        raise ExternalSceneError(f"{xml}: Mitsuba cannot load this scene: {first}{how}") from None


def external_sensor(mi, scene, width: int | None, height: int | None, move: dict | None = None, frame: int = 0):
    """A perspective sensor with the scene's first camera pose and field of view, our film; with ``move``
    (``{"kind", "amount", "frames"}``, render-scene --frames/--move) the pose of ``frame`` on that path:
    ``orbit``/``dolly`` about the look-at target (``look_distance``), ``sensors`` from the first camera to
    the scene's second perspective camera (field of view interpolated linearly), or still where the scene
    has only one."""
    from mcdenoise.render.buffers import make_sensor
    from mcdenoise.render.camera import dolly_path, orbit_path, sensor_path

    sensors = scene.sensors()
    if not sensors:
        raise ExternalSceneError("the scene has no sensor (camera) to render from")
    sensor = sensors[0]
    params = mi.traverse(sensor)
    if "x_fov" not in params:
        raise ExternalSceneError(f"the scene's camera is a {type(sensor).__name__}; only perspective cameras are supported")
    size = sensor.film().size()
    w = width or int(size[0])
    h = height or int(size[1])
    matrix = np.asarray(params["to_world"].matrix.numpy(), dtype=np.float64).reshape(4, 4)
    fov = float(params["x_fov"][0])
    if move:
        frames, kind, amount = int(move["frames"]), move["kind"], float(move.get("amount", 0.0))
        if kind in ("orbit", "dolly"):
            path = (orbit_path if kind == "orbit" else dolly_path)(matrix, look_distance(mi, scene, matrix), amount,
                                                                   frames)
            matrix = path[frame]
        elif kind == "sensors":
            second = [s for s in sensors[1:] if "x_fov" in mi.traverse(s)]
            if second:
                other = mi.traverse(second[0])
                end = np.asarray(other["to_world"].matrix.numpy(), dtype=np.float64).reshape(4, 4)
                try:
                    matrix = sensor_path(matrix, end, frames)[frame]
                except ValueError as exc:
                    raise ExternalSceneError(f"the scene's two cameras: {exc}") from None
                s = frame / (frames - 1) if frames > 1 else 0.0
                fov = (1 - s) * fov + s * float(other["x_fov"][0])
        else:
            raise ExternalSceneError(f"unknown camera move {kind!r}")
    return make_sensor(mi, mi.ScalarTransform4f(matrix), fov, w, h)


def look_distance(mi, scene, camera_to_world: np.ndarray) -> float:
    """How far ahead the camera's look-at target is (a scene file keeps only the camera's matrix, not the
    target it was made from): the first surface on the view axis; where the axis hits nothing, the
    scene's bounding-box centre's distance along it (or from the camera, when that centre is behind)."""
    origin = camera_to_world[:3, 3]
    forward = camera_to_world[:3, 2] / np.linalg.norm(camera_to_world[:3, 2])
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*map(float, origin)), mi.Vector3f(*map(float, forward))))
    hit = np.asarray(si.is_valid()).ravel()
    if hit.size and bool(hit[0]):
        return float(np.asarray(si.t).ravel()[0])
    bbox = scene.bbox()
    centre = (np.asarray(bbox.min, dtype=np.float64).ravel() + np.asarray(bbox.max, dtype=np.float64).ravel()) / 2
    along = float(np.dot(centre - origin, forward))
    return along if along > 0 else max(float(np.linalg.norm(centre - origin)), 1.0)


def external_notes(mi, scene) -> list[str]:
    """What of a user's scene our render leaves out, in words: render-scene says it once, so that a
    surprise in the images (no depth of field, clear glass where a medium was) has its reason."""
    notes = []
    camera = scene.sensors()[0]
    params = mi.traverse(camera)
    if "aperture_radius" in params and float(np.asarray(params["aperture_radius"]).ravel()[0]) > 0:
        notes.append("its thin-lens camera is rendered as a pinhole (no depth of field)")
    media = {id(m) for m in [camera.get_medium()]
             + [m for sh in scene.shapes() for m in (sh.interior_medium(), sh.exterior_medium())] if m is not None}
    if media:
        notes.append(f"its {len(media)} participating medi{'um is' if len(media) == 1 else 'a are'} not rendered "
                     "(our integrator traces surfaces only; a medium's boundary keeps its BSDF)")
    return notes


_CACHE: dict = {"scene_id": None, "scene": None, "features": None, "sensors": {}}


def frame_scene(mi, task: FrameTask):
    """The Mitsuba scene of ``task``, reusing the previous one when it is the same scene."""
    from mcdenoise.render.buffers import needed_features

    if _CACHE["scene_id"] == task.scene:
        return _CACHE["scene"], _CACHE["features"], 0.0
    _CACHE.update(scene_id=None, scene=None, features=None)
    gc.collect()
    t0 = time.perf_counter()
    if "xml" in task.desc:
        scene = load_external_scene(mi, task.desc["xml"], task.desc.get("defines"))
    else:
        from mcdenoise.render.scene import build_scene
        scene = build_scene(mi, task.desc)
    if task.render["features"] == "all":
        features = set(schema.OPTIONAL_FEATURES)
    else:
        features = needed_features(mi, scene)
    _CACHE.update(scene_id=task.scene, scene=scene, features=features)
    return scene, features, time.perf_counter() - t0


def frame_sensor(mi, task: FrameTask, scene):
    w, h = task.resolution or (None, None)
    if "xml" in task.desc:
        return external_sensor(mi, scene, w, h, task.desc.get("move"), task.frame)
    from mcdenoise.render.scene import build_sensor
    return build_sensor(mi, task.desc, task.frame, w, h)


def render_frame(task: FrameTask) -> dict:
    """Render the missing images of one frame, then write its ``frame.json``. Returns it."""
    t_start = time.perf_counter()
    store = Store(task.store)
    names = task.images or image_names(task.stacks)
    done = _already_rendered(store, task, names)
    if done is not None:
        return done
    _drop_temporary_files(store, task)
    mi = import_mitsuba(task.render["variant"], task.render["threads"])
    scene, features, build_s = frame_scene(mi, task)
    t0 = time.perf_counter()
    sensor = frame_sensor(mi, task, scene)
    build_s += time.perf_counter() - t0
    camera = sensor_camera(mi, sensor)
    records, gt_color, render_s, write_s, reused = _render_images(mi, scene, sensor, store, task, names, features,
                                                                  camera)
    w, h = camera.width, camera.height
    record = {
        "scene": task.scene, "frame": task.frame, "width": w, "height": h,
        "images": records, "features": sorted(features),
        "samples": int(w * h * sum(r["spp"] for r in records.values())),
        "nonfinite": sum(sum(r.get("nonfinite", {}).values()) for r in records.values()),
        "bytes": sum(r["bytes"] for r in records.values()),
        "timing": {"build": round(build_s, 4), "render": round(render_s, 4), "write": round(write_s, 4),
                   "total": round(time.perf_counter() - t_start, 4)},
        "reused_images": reused,
        **gt_summary(store, task, records, gt_color),
        # The camera frame (camera_to_world, columns: left, up, forward, origin) lets consumers turn the
        # world-space normals into camera space (train.data); with the field of view and clip
        # distances, the whole camera (pipeline.motion.camera_from_record: reprojection).
        **camera_record(camera),
    }
    if "xml" in task.desc:
        record["scene_notes"] = external_notes(mi, scene)
    if not task.images:
        store.write_frame_record(task.scene, task.frame, record)
    return record


def _already_rendered(store: Store, task: FrameTask, names) -> dict | None:
    """The frame's record marked ``skipped`` when all of ``names`` are on disk and recorded, else None."""
    # A task for a subset of the images (task.images) writes no frame.json, so it has none to go by.
    existing = store.frame_record(task.scene, task.frame) if not task.images else None
    if existing and all(n in existing.get("images", {}) and store.image_path(task.scene, task.frame, n).exists()
                        for n in names):
        return {**existing, "skipped": True}
    return None


def _drop_temporary_files(store: Store, task: FrameTask) -> None:
    """Remove the temporary files that interrupted writes left in the frame's folder."""
    # A SIGKILL during a write leaves its temporary file (never a partial image): drop them.
    # Only the task of this frame writes into this folder, so nothing live is removed.
    frame_dir = store.frame_dir(task.scene, task.frame)
    for tmp in frame_dir.glob(".*.tmp") if frame_dir.exists() else ():
        tmp.unlink(missing_ok=True)


def sensor_camera(mi, sensor) -> Camera:
    """The ``pipeline.motion.Camera`` of a perspective ``sensor`` (its pose, x field of view, film size
    and clip distances), written into the frame's record and every image's header."""
    params = mi.traverse(sensor)
    w, h = (int(v) for v in sensor.film().size())
    return Camera(np.asarray(sensor.world_transform().matrix.numpy(), np.float64).reshape(4, 4),
                  float(np.asarray(params["x_fov"]).ravel()[0]), w, h, float(sensor.near_clip()),
                  float(sensor.far_clip()))


def _render_images(mi, scene, sensor, store: Store, task: FrameTask, names, features, camera: Camera) -> tuple:
    """Render and write each image of ``names`` not already on disk: (records, ground-truth colours,
    render seconds, write seconds, number of images reused)."""
    records: dict[str, dict] = {}
    gt_color: dict[str, np.ndarray] = {}
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
        result, extra = render_one(mi, scene, sensor, task, name, features)
        render_s += result.seconds
        t0 = time.perf_counter()
        meta = {"image": name, "spp": extra.pop("spp"), "seed": task.seeds[name], "scene": task.scene,
                "frame": task.frame, "render_seconds": round(result.seconds, 4), "nonfinite": result.nonfinite,
                "features": sorted(features), **extra}
        records[name] = store.write_image(task.scene, task.frame, name, result.buffers, result.constants,
                                          meta, omit_constant=task.render["omit_constant"],
                                          encoding=task.render.get("encoding", "compact"), camera=camera)
        if name in GT_IMAGES:
            gt_color[name] = result.buffers["color"]
        write_s += time.perf_counter() - t0
    return records, gt_color, render_s, write_s, reused


def render_one(mi, scene, sensor, task: FrameTask, name: str, features) -> tuple:
    """One image of the frame: a stack in one render of stack_spp; a ground truth by the scene's stop
    rule (render.progressive). Returns the result and the extra header fields (spp; for a ground
    truth its estimated PSNR and the number of passes)."""
    from mcdenoise.render.buffers import render_image

    from .progressive import StopRule, render_to_target

    def render_pass(spp, seed):
        try:
            return render_image(mi, scene, sensor, spp=spp, seed=seed, features=features,
                                max_depth=task.render["max_depth"], rr_depth=task.render["rr_depth"])
        except RuntimeError as exc:   # say what Mitsuba said, not drjit's "(see above)" wrapper
            external = "xml" in task.desc
            where = task.desc["xml"] if external else f"frame {task.scene}/{task.frame:03d}"
            raise (ExternalSceneError if external else RenderFailed)(
                f"{where}: Mitsuba failed rendering {name}: {innermost_message(exc)}") from exc

    if name not in GT_IMAGES:
        return render_pass(task.stack_spp, task.seeds[name]), {"spp": task.stack_spp}
    rule = StopRule(task.gt_target_psnr, task.gt_pass_spp or task.gt_spp, task.gt_spp)
    r = render_to_target(render_pass, task.seeds[name], rule)
    extra = {"spp": r.spp, "estimated_psnr": _finite_psnr(r.estimated_psnr)}
    if rule.target_psnr is not None:
        extra["passes"] = r.passes
    return r, extra


def _finite_psnr(value: float) -> float:
    """A PSNR for JSON (which has no inf): identical images count as metrics.PSNR_CEILING."""
    return round(min(value, metrics.PSNR_CEILING), 3)


def gt_summary(store: Store, task: FrameTask, records: dict, gt_color: dict) -> dict:
    """The frame record's ``gt`` entry: spp reached and estimated PSNR per ground truth, and the
    measured PSNR of GT1 against GT2 (either may come from disk when the frame was resumed)."""
    if not all(n in records for n in GT_IMAGES):
        return {}
    for name in GT_IMAGES:
        if name not in gt_color:
            gt_color[name] = store.read_image(task.scene, task.frame, name, ["color"])[0]["color"]
    return {"gt": {"spp": {n: records[n]["spp"] for n in GT_IMAGES},
                   "estimated_psnr": {n: records[n].get("estimated_psnr") for n in GT_IMAGES},
                   "psnr_gt1_gt2": _finite_psnr(metrics.psnr(gt_color["gt1"], gt_color["gt2"]))}}
