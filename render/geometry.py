"""Object geometry: random shape parameters → triangle meshes (numpy arrays) for Mitsuba.

A shape is described by a small JSON dict (primitive kind and parameters, deformation, seed, or a
user mesh path, or explicit raw vertices/faces); ``mesh_arrays`` regenerates the same triangles from
it every time. Shapes other than ``raw`` are normalized to a unit bounding box centred at the origin,
so an object's size is set by its transform alone.
"""
from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np
import trimesh

from mcdenoise.render.rounding import rnd

PRIMITIVES = ("box", "icosphere", "uv_sphere", "cylinder", "capsule", "cone", "torus", "vase")
# Parts of assemblies only (render.furniture): random_primitive draws by index from PRIMITIVES, so new kinds
# live apart to leave the draws of existing scenes as they were.
PART_PRIMITIVES = ("frustum", "sweep")
MESH_EXTENSIONS = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
MAX_FACES = 10_000          # load_dict time grows with triangles; ~10k per mesh is the budget
SMOOTH_ANGLE_DEG = 35.0     # edges sharper than this stay hard (box edges, cylinder caps)


# --------------------------------------------------------------------------------------------
# Random parameters


def random_primitive(rng: np.random.Generator) -> dict:
    kind = PRIMITIVES[int(rng.integers(len(PRIMITIVES)))]
    u = lambda a, b: rnd(rng.uniform(a, b))  # noqa: E731
    if kind == "box":
        params = {"extents": [u(0.3, 1.0), u(0.3, 1.0), u(0.3, 1.0)]}
    elif kind == "icosphere":
        params = {"subdivisions": 4}
    elif kind == "uv_sphere":
        params = {"count": [32, 32]}
    elif kind in ("cylinder", "cone"):
        params = {"radius": u(0.2, 0.6), "height": u(0.3, 1.2), "sections": 48}
    elif kind == "capsule":
        params = {"radius": u(0.15, 0.4), "height": u(0.2, 1.0), "count": [24, 24]}
    elif kind == "torus":
        params = {"major_radius": u(0.3, 0.6), "minor_radius": u(0.05, 0.25),
                  "major_sections": 64, "minor_sections": 24}
    else:  # vase: a random smooth profile revolved around the vertical axis (bottles, bowls, lamps)
        n = int(rng.integers(3, 7))
        params = {"radii": [u(0.1, 0.6) for _ in range(n)], "height": u(0.5, 1.5), "sections": 48}
    return {"primitive": kind, "params": params}


def random_deform(rng: np.random.Generator) -> dict | None:
    """A smooth deformation (or None): displacement noise, twist, taper or bend."""
    if rng.uniform() < 0.45:
        return None
    kind = ("displace", "twist", "taper", "bend")[int(rng.integers(4))]
    if kind == "displace":
        return {"type": "displace", "amplitude": rnd(rng.uniform(0.02, 0.12)),
                "frequency": rnd(rng.uniform(2.0, 8.0)), "seed": int(rng.integers(2**31))}
    if kind == "twist":
        return {"type": "twist", "angle_deg": rnd(rng.uniform(-120, 120), 2)}
    if kind == "taper":
        return {"type": "taper", "amount": rnd(rng.uniform(-0.7, 0.7))}
    return {"type": "bend", "amount": rnd(rng.uniform(-1.0, 1.0))}


def random_shape(rng: np.random.Generator, group_probability: float, mesh_files: tuple[str, ...] = (),
                 mesh_probability: float = 0.0) -> dict:
    """Shape parameters: a user mesh, a group of primitives, or one (possibly deformed) primitive."""
    if mesh_files and rng.uniform() < mesh_probability:
        return {"kind": "file", "path": mesh_files[int(rng.integers(len(mesh_files)))]}
    if rng.uniform() < group_probability:
        parts = []
        for _ in range(int(rng.integers(2, 5))):
            part = random_primitive(rng)
            # Coarser tessellation for parts keeps a whole group near the per-mesh triangle budget.
            if part["primitive"] == "icosphere":
                part["params"]["subdivisions"] = 3
            elif part["primitive"] in ("uv_sphere", "capsule"):
                part["params"]["count"] = [20, 20]
            elif part["primitive"] == "torus":
                part["params"].update(major_sections=40, minor_sections=16)
            part["offset"] = [rnd(rng.uniform(-0.5, 0.5)) for _ in range(3)]
            part["scale"] = rnd(rng.uniform(0.3, 0.8))
            part["rotation_deg"] = [rnd(rng.uniform(0, 360), 2) for _ in range(3)]
            parts.append(part)
        return {"kind": "group", "parts": parts}
    shape = {"kind": "primitive", **random_primitive(rng)}
    shape["deform"] = random_deform(rng)
    return shape


# --------------------------------------------------------------------------------------------
# Meshes


def _primitive_mesh(kind: str, p: dict) -> trimesh.Trimesh:
    c = trimesh.creation
    if kind == "box":
        return c.box(extents=p["extents"])
    if kind == "icosphere":
        return c.icosphere(subdivisions=int(p["subdivisions"]))
    if kind == "uv_sphere":
        return c.uv_sphere(count=p["count"])
    if kind == "cylinder":
        return c.cylinder(radius=p["radius"], height=p["height"], sections=int(p["sections"]))
    if kind == "cone":
        return c.cone(radius=p["radius"], height=p["height"], sections=int(p["sections"]))
    if kind == "capsule":
        return c.capsule(radius=p["radius"], height=p["height"], count=p["count"])
    if kind == "torus":
        return c.torus(major_radius=p["major_radius"], minor_radius=p["minor_radius"],
                       major_sections=int(p["major_sections"]), minor_sections=int(p["minor_sections"]))
    if kind == "vase":
        radii = np.asarray(p["radii"], dtype=np.float64)
        # Smooth the control radii with a cubic-ish resampling, close the bottom and the top.
        t = np.linspace(0, 1, 24)
        r = np.interp(t * (len(radii) - 1), np.arange(len(radii)), radii)
        r = np.convolve(np.pad(r, 2, mode="edge"), np.ones(5) / 5, mode="valid")
        z = t * float(p["height"])
        profile = np.column_stack([np.concatenate([[0], r, [0]]), np.concatenate([[0], z, [z[-1]]])])
        m = c.revolve(profile, sections=int(p["sections"]))
        m.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))  # z-up → y-up
        return m
    if kind == "frustum":   # an open lamp shade: the side of a cone between two radii, no caps
        profile = np.array([[float(p["bottom"]), 0.0], [float(p["top"]), float(p["height"])]])
        m = c.revolve(profile, sections=int(p["sections"]))
        m.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
        return m
    if kind == "sweep":
        return _sweep(p)
    raise ValueError(f"unknown primitive {kind!r} (known: {', '.join(PRIMITIVES + PART_PRIMITIVES)})")


def _sweep(p: dict) -> trimesh.Trimesh:
    """A photo backdrop: a floor of ``depth`` running into a wall of ``height`` through a quarter circle of
    ``radius``, ``width`` wide along x (an open surface: render it two-sided)."""
    w, h, d, r = (float(p[k]) for k in ("width", "height", "depth", "radius"))
    a = np.linspace(0.0, np.pi / 2, int(p.get("sections", 16)))
    # profile (z, y): the floor from the front edge to the curve, the curve, the wall up to the top
    curve = np.column_stack([-(d - r) - r * np.sin(a), r - r * np.cos(a)])
    profile = np.vstack([[0.0, 0.0], curve, [-d, h]])
    k = len(profile)
    v = np.vstack([np.column_stack([np.full(k, x), profile[:, 1], profile[:, 0]]) for x in (-w / 2, w / 2)])
    f = [[i, i + 1, k + i + 1] for i in range(k - 1)] + [[i, k + i + 1, k + i] for i in range(k - 1)]
    return trimesh.Trimesh(v, np.asarray(f), process=True)


def _y_up(m: trimesh.Trimesh, kind: str) -> trimesh.Trimesh:
    # trimesh builds cylinders, cones, capsules and tori around z; our up axis is y.
    if kind in ("cylinder", "cone", "capsule", "torus"):
        m.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    return m


def _deform(m: trimesh.Trimesh, d: dict | None) -> trimesh.Trimesh:
    if not d:
        return m
    # Deformations need enough vertices to look smooth: subdivide long edges first.
    if len(m.faces) < 4000:
        for max_edge in (0.08, 0.12, 0.2):
            try:
                v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=max_edge, max_iter=10)
            except ValueError:  # needs more iterations than allowed: try coarser
                continue
            if len(f) <= MAX_FACES:
                m = trimesh.Trimesh(v, f, process=True)
                break
    v = m.vertices.copy()
    lo, hi = v.min(0), v.max(0)
    h = (v[:, 1] - lo[1]) / max(hi[1] - lo[1], 1e-9)  # 0 at the bottom, 1 at the top
    if d["type"] == "displace":
        rng = np.random.default_rng(int(d["seed"]))
        k = rng.normal(size=(8, 3)) * float(d["frequency"])
        ph = rng.uniform(0, 2 * np.pi, 8)
        noise = np.sin(v @ k.T + ph).sum(1) / np.sqrt(8)
        v = v + m.vertex_normals * (float(d["amplitude"]) * noise)[:, None]
    elif d["type"] == "twist":
        a = np.deg2rad(float(d["angle_deg"])) * (h - 0.5)
        ca, sa = np.cos(a), np.sin(a)
        v[:, 0], v[:, 2] = ca * v[:, 0] - sa * v[:, 2], sa * v[:, 0] + ca * v[:, 2]
    elif d["type"] == "taper":
        s = 1.0 + float(d["amount"]) * (h - 0.5)
        v[:, 0] *= s
        v[:, 2] *= s
    elif d["type"] == "bend":
        v[:, 0] += float(d["amount"]) * (h - 0.5) ** 2
    else:
        raise ValueError(f"unknown deformation {d['type']!r}")
    return trimesh.Trimesh(v, m.faces, process=False)


def _normalize(m: trimesh.Trimesh) -> trimesh.Trimesh:
    """Centre the bounding box at the origin and scale its largest side to 1."""
    lo, hi = m.bounds
    ext = float(np.max(hi - lo))
    m.apply_translation(-(lo + hi) / 2)
    if ext > 0:
        m.apply_scale(1.0 / ext)
    return m


def decimate(m: trimesh.Trimesh, max_faces: int = MAX_FACES) -> trimesh.Trimesh:
    """Vertex-clustering simplification (no extra dependency) down to at most max_faces faces."""
    if len(m.faces) <= max_faces:
        return m
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    lo, ext = v.min(0), max(float(np.ptp(v, axis=0).max()), 1e-12)
    for res in (256, 160, 128, 96, 64, 48, 32, 24, 16, 8):
        q = np.floor((v - lo) / ext * res).astype(np.int64)
        _, inv, counts = np.unique(q, axis=0, return_inverse=True, return_counts=True)
        inv = inv.ravel()
        nf = inv[f]
        nf = nf[(nf[:, 0] != nf[:, 1]) & (nf[:, 1] != nf[:, 2]) & (nf[:, 0] != nf[:, 2])]
        idx = np.unique(np.sort(nf, axis=1), axis=0, return_index=True)[1]  # drop duplicated faces
        if len(idx) <= max_faces:
            faces = nf[np.sort(idx)]
            nv = np.zeros((len(counts), 3))
            np.add.at(nv, inv, v)
            nv /= counts[:, None]
            return trimesh.Trimesh(nv, faces, process=True)
    return m


@functools.lru_cache(maxsize=8)
def list_mesh_files(dirs: tuple[str, ...]) -> tuple[str, ...]:
    """Sorted mesh files under the given folders (recursive); cached, so a worker lists once."""
    files = []
    for d in dirs:
        for root, _, names in os.walk(d):
            files += [str(Path(root) / n) for n in names if n.lower().endswith(MESH_EXTENSIONS)]
    return tuple(sorted(files))


@functools.lru_cache(maxsize=32)
def _load_user_mesh(path: str) -> trimesh.Trimesh:
    m = trimesh.load(path, force="mesh")
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise ValueError(f"{path}: no triangles found")
    m = trimesh.Trimesh(m.vertices, m.faces, process=True)  # drop UVs/visuals: we texture ourselves
    return _normalize(decimate(m))


def base_mesh(shape: dict) -> trimesh.Trimesh:
    """The untransformed mesh of a shape description (normalized unless raw)."""
    kind = shape["kind"]
    if kind == "primitive":
        m = _y_up(_primitive_mesh(shape["primitive"], shape["params"]), shape["primitive"])
        return _normalize(_deform(_normalize(m), shape.get("deform")))
    if kind == "group":
        parts = []
        for part in shape["parts"]:
            m = _normalize(_y_up(_primitive_mesh(part["primitive"], part["params"]), part["primitive"]))
            m.apply_scale(float(part["scale"]))
            m.apply_transform(trimesh.transformations.euler_matrix(*np.deg2rad(part["rotation_deg"])))
            m.apply_translation(part["offset"])
            parts.append(m)
        return _normalize(trimesh.util.concatenate(parts))
    if kind == "assembly":
        return assembly_mesh(shape["parts"])
    if kind == "file":
        return _load_user_mesh(str(shape["path"])).copy()
    if kind == "raw":
        return trimesh.Trimesh(np.asarray(shape["vertices"], float), np.asarray(shape["faces"], int), process=False)
    raise ValueError(f"unknown shape kind {kind!r}")


def _unit_box(m: trimesh.Trimesh) -> trimesh.Trimesh:
    """Centre the bounding box at the origin and scale every side to 1 (a flat side stays flat)."""
    lo, hi = m.bounds
    ext = np.where(hi - lo > 1e-9, hi - lo, 1.0)
    m.apply_translation(-(lo + hi) / 2)
    m.apply_transform(np.diag([*(1.0 / ext), 1.0]))
    return m


def assembly_mesh(parts: list) -> trimesh.Trimesh:
    """Furniture and props: primitives each fitted to its own box (``size``, per axis), turned by
    ``rotation_deg`` and put at ``position`` (its box's centre), in one mesh in the object's own units
    (not normalized: a table is as large as its parts say)."""
    meshes = []
    for part in parts:
        m = _unit_box(_y_up(_primitive_mesh(part["primitive"], part.get("params", {})), part["primitive"]))
        m.apply_transform(transform_matrix({"scale": part["size"], "rotation_deg": part.get("rotation_deg", [0, 0, 0]),
                                            "position": part["position"]}))
        meshes.append(m)
    return trimesh.util.concatenate(meshes)


def transform_matrix(tf: dict) -> np.ndarray:
    """4x4 matrix of scale (scalar or per-axis), then XYZ Euler rotation, then translation."""
    s = np.broadcast_to(np.asarray(tf.get("scale", 1.0), float), (3,))
    mat = np.diag([*s, 1.0])
    mat = trimesh.transformations.euler_matrix(*np.deg2rad(tf.get("rotation_deg", [0, 0, 0]))) @ mat
    mat[:3, 3] = tf.get("position", [0, 0, 0])
    return mat


def mesh_arrays(shape: dict, tf: dict, uv_scale: float = 1.0) -> dict:
    """Transformed triangles ready for mi.Mesh: positions (N,3), faces (F,3), normals (N,3) or None, uvs.

    ``tf["rest_on_ground"]`` lifts the rotated mesh so its lowest point sits at ``position[1]``.
    Faces are unmerged so each triangle gets box-projected UVs (planar along its dominant axis, in
    object units, so textures do not stretch with the object's proportions); smooth normals come from
    trimesh's angle-thresholded smoothing, keeping sharp edges sharp.
    """
    m = base_mesh(shape)
    raw = shape["kind"] == "raw"
    mat = transform_matrix(tf)
    if tf.get("rest_on_ground"):
        m.apply_transform(transform_matrix({**tf, "position": [0, 0, 0]}))
        lo = m.bounds[0][1] if len(m.vertices) else 0.0
        m.apply_translation([tf["position"][0], tf["position"][1] - lo, tf["position"][2]])
    else:
        m.apply_transform(mat)
    f = np.asarray(m.faces, dtype=np.int64)
    if raw:
        # Degenerate test geometry goes to Mitsuba as is: no normals (Mitsuba uses face normals).
        v = np.asarray(m.vertices, np.float64)
        uv = v[:, [0, 2]] * uv_scale
        return {"positions": v, "faces": f, "normals": None, "uvs": uv}
    sm = trimesh.graph.smooth_shade(m, angle=np.deg2rad(SMOOTH_ANGLE_DEG))
    sv, sf = np.asarray(sm.vertices), np.asarray(sm.faces)
    corner_v = sv[sf].reshape(-1, 3)
    corner_n = np.asarray(sm.vertex_normals)[sf].reshape(-1, 3)
    fn = np.asarray(sm.face_normals)
    # Degenerate faces (e.g. a box flattened to zero thickness) have no normal: fall back to the
    # face normal, then to +y, so Mitsuba never sees NaN or zero-length shading normals.
    fn_c = np.repeat(fn, 3, axis=0)
    bad = ~np.isfinite(corner_n).all(1) | (np.linalg.norm(corner_n, axis=1) < 0.5)
    corner_n[bad] = fn_c[bad]
    bad = ~np.isfinite(corner_n).all(1) | (np.linalg.norm(corner_n, axis=1) < 0.5)
    corner_n[bad] = [0.0, 1.0, 0.0]
    fn = np.where(np.isfinite(fn), fn, 0.0)
    axis = np.argmax(np.abs(fn), axis=1)
    # Planar projection per face: drop the dominant normal axis.
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis]                    # (F, 2)
    uv = np.take_along_axis(sv[sf], np.repeat(keep[:, None, :], 3, axis=1), axis=2).reshape(-1, 2)
    scale = float(np.max(np.broadcast_to(np.asarray(tf.get("scale", 1.0), float), (3,))))
    uv = uv / max(scale, 1e-9) * uv_scale
    faces = np.arange(len(corner_v), dtype=np.int64).reshape(-1, 3)
    return {"positions": corner_v, "faces": faces, "normals": corner_n, "uvs": uv}
