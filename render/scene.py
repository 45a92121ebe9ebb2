"""Scene randomizer (paper §3.1): random objects, materials, textures and lights, and a random
camera move over the frames of a scene.

A scene lives as a JSON *description* (plain dicts, lists, numbers and strings) stored in the
dataset manifest; ``build_scene`` turns it into a Mitsuba scene, regenerating meshes and textures
from the parameters (and seeds) inside it, so the same description always gives the same scene.

Conventions: y is up, the ground is the plane y = 0, lengths are in units of roughly one object,
colours are linear RGB, angles in degrees.
"""
from __future__ import annotations

import numpy as np

from mcdenoise.render import camera as cam, lights as lt
from mcdenoise.render.buffers import make_sensor
from mcdenoise.render.geometry import list_mesh_files, mesh_arrays
from mcdenoise.render.interior import interior_scene
from mcdenoise.render.layout import enclosed_room, ground, place_objects, room_walls, surface_material
from mcdenoise.render.materials import TextureCache, bsdf_dict
from mcdenoise.render.product import product_scene
from mcdenoise.render.stress import STRESS_PRESETS, stress_description

DESC_VERSION = 1

__all__ = ["random_scene", "scene_kind", "build_scene", "build_sensor", "STRESS_PRESETS", "stress_scene", "DESC_VERSION"]


def random_scene(cfg, seed: int, index: int, frames: int) -> dict:
    """The description of random scene ``index`` of a dataset with master ``seed``.

    Deterministic in (seed, index, cfg, frames): its own ``np.random.default_rng([seed, index])``. A furnished
    interior with ``interior_probability``, else a product shot with ``product_probability`` (render.interior,
    render.product), else objects on a ground.
    """
    kind = scene_kind(cfg, seed, index)
    if kind != "objects":
        desc = (interior_scene if kind == "interior" else product_scene)(cfg, seed, index, frames)
        return {**desc, "version": DESC_VERSION}
    rng = np.random.default_rng([int(seed), int(index)])
    mesh_files = list_mesh_files(tuple(str(d) for d in cfg.mesh_dirs)) if cfg.mesh_dirs else ()
    n_obj = int(rng.integers(int(cfg.objects[0]), int(cfg.objects[1]) + 1))
    objects, center, radius = place_objects(rng, cfg, n_obj, mesh_files)
    if not objects:  # objects: [0, 0] → frame an empty patch of ground
        center, radius = [0.0, 0.5, 0.0], 1.0
    c = np.asarray(center)
    camera = cam.random_camera(rng, c, radius, cfg.fov, float(cfg.camera_move), int(frames))
    room_half = camera["max_distance"] * 1.15 + 0.5 * radius   # the camera path stays inside the room
    lights, environment, total = _random_lights(rng, cfg, camera, center, c, radius, room_half)
    walls, floor = _random_walls_and_ground(rng, cfg, camera, lights, center, c, radius, room_half)
    # Closed rooms lit through windows draw from their own stream, so that the scenes of a config without
    # them (enclosed_probability 0) are exactly what they were before the key existed.
    enclosed = np.random.default_rng([int(seed), int(index), 1])
    if cfg.enclosed_probability > 0 and enclosed.uniform() < cfg.enclosed_probability:
        walls, floor, lights, environment = _enclose(enclosed, cfg, camera, c, radius, room_half, lights, total)
    environment = _maybe_delta_sun(cfg, seed, index, environment)
    return {
        "version": DESC_VERSION, "seed": int(seed), "index": int(index), "preset": None, "frames": int(frames),
        "cluster": {"center": center, "radius": radius},
        "objects": objects, "ground": floor, "walls": walls, "lights": lights, "environment": environment,
        "camera": camera,
    }


def scene_kind(cfg, seed: int, index: int) -> str:
    """"interior", "product" or "objects": which generator draws scene ``index``."""
    # A stream of its own, drawn from only when a kind is asked for: configs without the keys (both 0) draw
    # exactly the scenes they drew before the keys existed.
    if cfg.interior_probability <= 0 and cfg.product_probability <= 0:
        return "objects"
    draw = np.random.default_rng([int(seed), int(index), 3]).uniform(size=2)
    if draw[0] < cfg.interior_probability:
        return "interior"
    return "product" if draw[1] < cfg.product_probability else "objects"


def _random_lights(rng, cfg, camera, center, c, radius, room_half) -> tuple:
    """The scene's lights and environment from a light budget; returns (lights, environment, total budget)."""
    # Light budget: a total irradiance at the cluster, split at random between the sources.
    n_area = int(rng.integers(int(cfg.area_lights[0]), int(cfg.area_lights[1]) + 1))
    small = [bool(rng.uniform() < cfg.small_light_probability) for _ in range(n_area)]
    has_point = bool(rng.uniform() < cfg.point_light_probability)
    has_spot = bool(rng.uniform() < cfg.spot_light_probability)
    has_env = bool(rng.uniform() < cfg.environment_probability)
    if n_area + has_point + has_spot + has_env == 0:
        has_env = True  # never a black scene
    share = rng.dirichlet(np.ones(n_area + has_point + has_spot + has_env))
    total = float(np.exp(rng.uniform(np.log(3.0), np.log(10.0))))  # calibrated: frame means ~0.03-0.6
    budgets = iter(share * total)
    max_dist = 0.85 * room_half
    # Directions from the cluster to the camera: lights there would hide the objects.
    avoid = [np.subtract(p["origin"], center) / np.linalg.norm(np.subtract(p["origin"], center))
             for p in camera["frames"]]
    lights = [lt.area_light(rng, c, radius, max_dist, next(budgets), s, avoid) for s in small]
    if has_point:
        lights.append(lt.point_light(rng, c, radius, max_dist, next(budgets)))
    if has_spot:
        lights.append(lt.spot_light(rng, c, radius, max_dist, next(budgets)))
    environment = lt.random_environment(rng, next(budgets)) if has_env else None
    return lights, environment, total


def _random_walls_and_ground(rng, cfg, camera, lights, center, c, radius, room_half) -> tuple:
    """Walls behind the objects (with probability ``walls_probability``) and the ground: (walls, floor)."""
    walls: list = []
    if rng.uniform() < cfg.walls_probability:
        sides = [s for s in ("+x", "-x", "+z", "-z") if rng.uniform() < 0.6] or ["+x"]
        height = _room_height(rng, camera, lights, c, radius)
        ceiling = bool(rng.uniform() < 0.25)
        wall_mat = surface_material(rng, cfg.texture_probability, 2 * room_half, radius * rng.uniform(1.0, 4.0),
                                    cfg.polished_probability)
        walls = room_walls(center, room_half, height, sides, wall_mat, ceiling)
        ground_size = 2 * room_half
    else:
        ground_size = max(40.0 * radius, 4 * room_half)
    floor = ground(center, ground_size, surface_material(rng, cfg.texture_probability, ground_size,
                                                         radius * rng.uniform(1.0, 4.0), cfg.polished_probability))
    return walls, floor


def _maybe_delta_sun(cfg, seed: int, index: int, environment):
    """The environment with its sun made a delta light, with probability ``sun_delta_probability``."""
    # Delta suns draw from a stream of their own too (the same reason as enclosed rooms).
    if cfg.sun_delta_probability > 0 and environment and environment.get("sun"):
        if np.random.default_rng([int(seed), int(index), 2]).uniform() < cfg.sun_delta_probability:
            environment = {**environment, "sun": {**environment["sun"], "delta": True}}
    return environment


def _room_height(rng, camera, lights, c, radius) -> float:
    """A ceiling height above every camera position and light, and above the objects."""
    tops = [p["origin"][1] for p in camera["frames"]]
    tops += [light.get("center", light.get("position", [0, 0, 0]))[1] for light in lights]
    return max(max(tops) * rng.uniform(1.15, 1.6), c[1] + 2 * radius) + 0.2 * radius


def _enclose(rng, cfg, camera, c, radius, room_half, lights, total):
    """Walls, floor, lights and sky of the scene moved into a closed room lit through its windows: a sky
    (with a sun 70 % of the time) ten times the scene's light budget outside, and half the time none of
    the drawn lights inside (daylight only), else the drawn lights as well."""
    height = _room_height(rng, camera, lights, c, radius)
    center = [float(c[0]), 0.0, float(c[2])]
    material = surface_material(rng, cfg.texture_probability, 2 * room_half, radius * rng.uniform(1.0, 4.0),
                                cfg.polished_probability)
    walls = enclosed_room(rng, center, room_half, height, material)
    floor = ground(center, 2 * room_half, surface_material(rng, cfg.texture_probability, 2 * room_half,
                                                            radius * rng.uniform(1.0, 4.0), cfg.polished_probability))
    sky = lt.random_environment(rng, 10.0 * total)
    while sky["type"] != "sky" or (sky["sun"] is None and rng.uniform() < 0.36):   # 70 % with a sun
        sky = lt.random_environment(rng, 10.0 * total)
    return walls, floor, (lights if rng.uniform() < 0.5 else []), sky


def stress_scene(name: str, seed: int, frames: int) -> dict:
    """The description of a named stress preset (see render/stress.py); ValueError for unknown names."""
    desc = stress_description(name, seed, frames)
    desc.setdefault("version", DESC_VERSION)
    return desc


# --------------------------------------------------------------------------------------------
# Building


def _mesh(mi, name: str, arrays: dict, bsdf):
    """An in-memory mi.Mesh (no temporary files) with the given BSDF object."""
    props = mi.Properties()
    props["bsdf"] = bsdf
    v, f, n, uv = arrays["positions"], arrays["faces"], arrays["normals"], arrays["uvs"]
    mesh = mi.Mesh(name, len(v), len(f), props=props, has_vertex_normals=n is not None, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(v, dtype=np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(f, dtype=np.uint32).ravel())
    if n is not None:
        params["vertex_normals"] = mi.Float(np.ascontiguousarray(n, dtype=np.float32).ravel())
    params["vertex_texcoords"] = mi.Float(np.ascontiguousarray(uv, dtype=np.float32).ravel())
    params.update()
    return mesh


def _rect_dict(mi, r: dict, tex: TextureCache) -> dict:
    T = mi.ScalarTransform4f
    c, n = np.asarray(r["center"], float), np.asarray(r["normal"], float)
    w, h = r["size"]
    to_world = T().look_at(origin=c.tolist(), target=(c + n).tolist(), up=r["up"]) @ T().scale([w / 2, h / 2, 1.0])
    # Inner walls between two rooms are seen from both sides (two_sided); older descriptions lack the key.
    d = {"type": "rectangle", "to_world": to_world, "bsdf": bsdf_dict(r["material"], tex, bool(r.get("two_sided")))}
    if r.get("emitter"):
        d["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": r["emitter"]["radiance"]}}
    return d


def build_scene(mi, desc: dict, max_depth: int = 8):
    """The Mitsuba scene of a description, without a sensor (the renderer makes its own, see
    ``build_sensor``). A default ``path`` integrator is included because wrapping a scene that has
    none crashed Mitsuba natively; renderers pass their own integrator anyway."""
    tex = TextureCache(mi)
    scene: dict = {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth)}}
    for i, obj in enumerate(desc.get("objects", [])):
        uv_arrays = mesh_arrays(obj["shape"], obj["transform"])
        if len(uv_arrays["faces"]) == 0:
            continue
        bsdf = mi.load_dict(bsdf_dict(obj["material"], tex, two_sided=bool(obj.get("two_sided"))))
        scene[f"obj_{i:03d}"] = _mesh(mi, obj.get("name", f"object_{i}"), uv_arrays, bsdf)
    if desc.get("ground"):
        scene["ground"] = _rect_dict(mi, desc["ground"], tex)
    for i, wall in enumerate(desc.get("walls", [])):
        scene[f"wall_{i:02d}"] = _rect_dict(mi, wall, tex)
    for i, light in enumerate(desc.get("lights", [])):
        scene[f"light_{i:02d}"] = lt.emitter_dicts(mi, light)
    if desc.get("environment"):
        scene["environment"] = lt.environment_dict(mi, desc["environment"])
        if lt.is_delta_sun(desc["environment"]):
            scene["sun"] = lt.sun_dict(desc["environment"])
    # The order of shapes and emitters decides which light a given random number selects, so it
    # must be fixed for a seed to reproduce an image. Parallel loading appends objects in
    # thread-timing order, and the 'optimize' pass (merging identical objects) reorders them
    # too (measured: up to 4 orders in 15 loads of one scene); with both off the scene keeps
    # the description's order in every process (tests/test_dataset.py checks reruns bitwise).
    return mi.load_dict(scene, parallel=False, optimize=False)


def build_sensor(mi, desc: dict, frame: int, width: int, height: int):
    """The perspective sensor (box filter, see render.buffers) of frame ``frame`` of the camera move."""
    poses = desc["camera"]["frames"]
    if not 0 <= frame < len(poses):
        raise IndexError(f"frame {frame} out of range: the scene has {len(poses)} frames")
    pose = poses[frame]
    return make_sensor(mi, cam.to_world(mi, pose), float(pose["fov"]), int(width), int(height))
