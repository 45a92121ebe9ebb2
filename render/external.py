"""User-supplied Mitsuba 3 XML scenes, rendered with their own camera but our buffers.

The scene's own integrator and film are replaced: every image goes through our split-buffer
integrator with a box-filtered film (``render.buffers.make_sensor``), at our sample counts, with the path
depths the scene's integrator sets (``max_depth``, ``rr_depth``: kept, and said), so a
production scene lands in the store exactly like a test frame of the random dataset. The frame
worker loads the XML and builds that camera (``render.frame.load_external_scene``,
``external_sensor``; a scene it cannot use raises ``render.frame.ExternalSceneError``).

``render_scene`` (``python -m pipeline render-scene SCENE.xml [-D name=value ...] --store STORE``; the
``-D`` values fill the XML's ``$name`` parameters, as on Mitsuba's command line) puts a user's scene
into the split ``external`` of the store (created if needed) as one frame with the same images as
a dataset frame (GT1, GT2, stacks), rendered by the same worker code.

``--frames N`` renders frames 000..N-1 along a camera path that starts at the scene's camera
(``render.camera``): ``--move orbit:DEGREES`` turns it about the look-at target (the first surface on
its view axis: ``render.frame.look_distance``) by that angle over the frames, ``--move dolly:FRACTION``
moves it that fraction of the distance towards the target; without ``--move`` the frames go from the
scene's first perspective camera to its second (a hand-made scene carries its own move that way; the
camera stays still where there is no second). Every frame records its camera (frame.json, EXR headers).
A rerun keeps the images on disk (it resumes), so it must ask for the same camera path: one with another
``--frames``/``--move`` is refused (``check_rerun``).
"""
from __future__ import annotations

import dataclasses
import re
import shutil
from pathlib import Path

from mcdenoise.pipeline.config import Config, ConfigError
from mcdenoise.pipeline.executors import run_tasks
from mcdenoise.pipeline.exr import StoreError, atomic_write_bytes
from mcdenoise.pipeline.store import STORE_FORMAT, STORE_VERSION, Store, image_names, image_seed
from mcdenoise.pipeline.versions import package_versions

EXTERNAL_SPLIT = "external"
# External scenes take seeds from a range no random scene reaches (scene index >= 2^20).
_EXTERNAL_INDEX_BASE = 1 << 20


# Most frames of one external scene (render-scene --frames).
MAX_FRAMES = 100
# Frame f of the scene at position i of the external split seeds its images from the counter
# (2^20·(1+f) + i)·images + k (frame_seeds, pipeline.store.image_seed), a distinct 32-bit value while
# (frames + 1)·images <= 2^12 (i < 2^20): 100 frames of up to 38 stacks. seed_range checks it.
_SEED_COUNTERS = 1 << 12

# load_file's own keywords: a scene parameter of that name could not be passed to it.
_RESERVED = ("path", "parallel", "optimize", "update_scene")


def parse_defines(items: list[str] | None) -> dict[str, str]:
    """``-D NAME=VALUE`` arguments (Mitsuba's command line: values of the XML's ``$NAME`` parameters) as
    ``{NAME: VALUE}``; a later one of the same name wins, as there."""
    out: dict[str, str] = {}
    for item in items or []:
        m = re.fullmatch(r"([A-Za-z_][A-Za-z0-9_]*)=(.*)", item, flags=re.S)
        if not m:
            raise ConfigError(f"-D {item!r}: expected NAME=VALUE (a scene parameter $NAME of the XML), e.g. -D spp=64")
        if m.group(1) in _RESERVED:
            raise ConfigError(f"-D {item!r}: {m.group(1)!r} cannot be passed to Mitsuba's loader (one of its own "
                              f"arguments: {', '.join(_RESERVED)}); rename the parameter in the XML")
        out[m.group(1)] = m.group(2)
    return out


def scene_id(xml: str, name: str | None) -> str:
    sid = name or "ext_" + re.sub(r"[^A-Za-z0-9_-]+", "_", Path(xml).stem)
    if not re.fullmatch(r"[A-Za-z0-9_-]{1,64}", sid):
        raise ConfigError(f"--name {sid!r}: use 1-64 letters, digits, '_' or '-'")
    return sid


def _register(store: Store, cfg: Config, sid: str) -> int:
    """Add ``sid`` to the store's external split; returns its index for seeding."""
    if store.manifest_path.exists():
        m = store.manifest()
    else:
        m = {"format": STORE_FORMAT, "version": STORE_VERSION, "config": dataclasses.asdict(cfg),
             "scenes": [], "splits": {"train": [], "val": [], "test": []}, "packages": package_versions()}
    ext = m["splits"].setdefault(EXTERNAL_SPLIT, [])
    if sid not in ext:
        ext.append(sid)
    if sid not in m["scenes"]:
        m["scenes"].append(sid)
    store.write_manifest({k: v for k, v in m.items() if k not in ("format", "version")})
    return _EXTERNAL_INDEX_BASE + ext.index(sid)


def camera_move(frames: int, move: str | None) -> dict | None:
    """The scene description's ``move`` for ``--frames``/``--move`` (None for a single frame, so its
    description is what it always was); ConfigError in one line for values that cannot be rendered."""
    from .camera import parse_move
    if not 1 <= frames <= MAX_FRAMES:
        raise ConfigError(f"--frames {frames}: render 1 to {MAX_FRAMES} frames of a scene")
    if move is not None and frames == 1:
        raise ConfigError(f"--move {move!r} needs --frames 2 or more (one frame does not move)")
    if frames == 1:
        return None
    if move is None:
        return {"kind": "sensors", "frames": frames}
    try:
        kind, amount = parse_move(move)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    return {"kind": kind, "amount": amount, "frames": frames}


def seed_range(frames: int, stacks: int) -> None:
    """ConfigError in one line where ``frames`` frames of ``stacks`` stacks would need seed counters past
    2^32 (two images of the store would then share a seed)."""
    images = len(image_names(stacks))
    if (frames + 1) * images > _SEED_COUNTERS:
        most = _SEED_COUNTERS // images - 1
        raise ConfigError(f"--frames {frames} with dataset.stacks={stacks}: the frames' seeds would pass 2^32 "
                          f"(at most {most} frames of {stacks} stacks, or {_SEED_COUNTERS // (frames + 1) - 2} "
                          f"stacks of {frames} frames)")


def _move_words(move: dict | None) -> str:
    """A scene description's ``move`` as render-scene's arguments."""
    if move is None:
        return "--frames 1"
    amount = f" --move {move['kind']}:{move['amount']:g}" if "amount" in move else ""
    return f"--frames {move['frames']}{amount}"


def check_rerun(store: Store, sid: str, move: dict | None) -> None:
    """ConfigError in one line when ``sid``'s folder was rendered along another camera path (frame count or
    move): a rerun keeps the images already on disk (it resumes an interrupted render) and frame k's pose is
    k/(N-1) of the move, so the frames would mix two paths."""
    if not (store.scene_dir(sid) / "scene.json").exists():
        return
    before = store.scene_manifest(sid).get("description", {}).get("move")
    if before != move:
        raise ConfigError(f"{store.scene_dir(sid)}: rendered with {_move_words(before)}, not {_move_words(move)}; "
                          "its frames would mix two camera paths: delete the folder or give the scene another --name")


def render_scene(xml: str, store_path: str, cfg: Config, resolution: str | None = None,
                 name: str | None = None, defines: dict[str, str] | None = None, frames: int = 1,
                 move: str | None = None) -> dict:
    """Render ``xml`` (its ``$name`` parameters from ``defines``) into the store's external split: one
    frame, or ``frames`` along ``move`` (module docstring)."""
    path_move = camera_move(frames, move)
    seed_range(frames, cfg.dataset.stacks)
    if not Path(xml).is_file():
        raise StoreError(f"{xml}: scene file not found")
    size = None
    if resolution:
        m = re.fullmatch(r"(\d+)x(\d+)", resolution)
        if not m or int(m.group(1)) < 1 or int(m.group(2)) < 1:
            raise ConfigError(f"--resolution {resolution!r}: expected WxH, e.g. 256x256")
        size = (int(m.group(1)), int(m.group(2)))
    store = Store(store_path)
    sid = scene_id(xml, name)
    desc = {"xml": str(Path(xml).resolve()), **({"defines": dict(sorted(defines.items()))} if defines else {}),
            **({"move": path_move} if path_move else {})}
    check_rerun(store, sid, path_move)
    # A scene that fails (bad XML, a render error) leaves the store as it found it: the manifest
    # gets its old bytes back, a new scene folder goes, a store this call created is removed.
    root_existed = store.root.exists()
    manifest = store.manifest_path.read_bytes() if store.manifest_path.exists() else None
    folder_existed = store.scene_dir(sid).exists()
    try:
        return _render(store, store_path, cfg, xml, sid, size, desc)
    except BaseException:
        if not root_existed:
            shutil.rmtree(store.root, ignore_errors=True)
        else:
            if manifest is None:
                store.manifest_path.unlink(missing_ok=True)
            else:
                atomic_write_bytes(store.manifest_path, lambda tmp: Path(tmp).write_bytes(manifest))
            if not folder_existed:
                shutil.rmtree(store.scene_dir(sid), ignore_errors=True)
        raise


def scene_depths(xml: str, defines: dict[str, str]) -> dict[str, int]:
    """The path depths the scene's own integrator sets (``max_depth``, ``rr_depth`` of the first integrator that
    names them, nested ones included, ``$name`` values from ``defines`` or the XML's ``<default>``); {} where it
    sets none or the XML cannot be read here (Mitsuba reports that when it loads the scene)."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(xml).getroot()
    except (ET.ParseError, OSError):
        return {}
    values = {d.get("name"): d.get("value") for d in root.iter("default")}
    values.update(defines)
    found: dict[str, int] = {}
    for integrator in root.iter("integrator"):
        for prop in integrator.findall("integer"):
            key, text = prop.get("name"), str(prop.get("value", ""))
            text = values.get(text[1:], text) if text.startswith("$") else text
            if key in ("max_depth", "rr_depth") and key not in found and re.fullmatch(r"-?\d+", str(text)):
                found[key] = int(text)
    return found


def frame_seeds(master: int, index: int, frame: int, names: list[str]) -> dict[str, int]:
    """Seeds of one frame of an external scene. Frame f counts as scene ``index + f * 2^20`` of one frame:
    frame 0 keeps the seeds a single-frame render always had, and later frames take ranges no random
    scene (index < 2^20) and no other external frame reaches."""
    return {n: image_seed(master, index + frame * _EXTERNAL_INDEX_BASE, 0, k, 1, len(names))
            for k, n in enumerate(names)}


def _render(store: Store, store_path: str, cfg: Config, xml: str, sid: str, size, desc: dict) -> dict:
    from .dataset import render_frame_entry, scene_record, task_spp
    from .frame import FrameTask

    index = _register(store, cfg, sid)
    d = cfg.dataset
    names = image_names(d.stacks)
    frames = desc["move"]["frames"] if "move" in desc else 1
    seeds = {str(f): frame_seeds(cfg.seed, index, f, names) for f in range(frames)}
    record = scene_record(cfg, sid, index, EXTERNAL_SPLIT, None, frames, list(size) if size else None, seeds, desc)
    own = scene_depths(xml, desc.get("defines", {}))    # the scene's own path depths are part of its look: kept
    record["integrator"].update(own)
    store.write_scene_manifest(sid, {**record, "packages": package_versions()})
    render = dataclasses.asdict(cfg.render)
    for key, value in own.items():
        if value != render[key]:
            print(f"render-scene: {sid}: the scene's integrator {key}={value} kept (render.{key}={render[key]} "
                  "is the random scenes')")
    render.update(own)
    tasks = [FrameTask(store=str(store_path), scene=sid, frame=f, desc=desc, resolution=size,
                       seeds=seeds[str(f)], render=render, **task_spp(record)) for f in range(frames)]
    stats = {"failed": 0}
    notes: list[str] = []
    for task, result, error in run_tasks(tasks, render_frame_entry, cfg.executor):
        if error is not None:
            raise StoreError(str(error).strip().splitlines()[-1] if str(error).strip() else repr(error))
        print(f"render-scene: {sid} -> {store.frame_dir(sid, task.frame)}: {result['width']}x{result['height']}, "
              f"{len(result['images'])} images, {result['timing']['total']:.1f} s, "
              f"{result['nonfinite']} non-finite values repaired")
        notes = result.get("scene_notes", notes)
    for note in notes:
        print(f"render-scene: {sid}: note: {note}")
    if frames > 1:
        print(f"render-scene: denoise it: python -m pipeline denoise --sequence '{store.scene_dir(sid)}/###/s00.exr' "
              f"--spp {record['stack_spp']} --out '{sid}_###.exr'")
    else:
        print(f"render-scene: denoise it: python -m pipeline denoise --store {store_path} --frame {sid}/000 "
              f"--spp {record['stack_spp']} --out {sid}.exr")
    return stats
