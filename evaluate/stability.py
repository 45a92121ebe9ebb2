"""``make stability`` → ``python -m pipeline stability``: every method on inputs that break denoisers.

Each case is a synthetic buffer dictionary built here with every channel of the schema (each
buffer and its variance, as ``Store.read`` returns them): fireflies of 1e4 on a dark frame, an
all-black frame, radiance 1e5 everywhere, NaN and ±Inf pixels, zero albedo, zero-length and
garbage normals, 8×8, non-square and odd sizes, and (``eval.stability_large``) a 1920×1080 frame.
Every method of ``eval.methods`` runs on every case through the evaluation harness
(``evaluate.harness.run_method``): NaN/Inf inputs are repaired to 0 and counted *before* a method
sees them; a run passes when it returns a finite (H, W, 3) image. Exceptions, wrong shapes and
non-finite outputs are reported as failures, with times. Output ranges are kept in the JSON (for
instance how much of the 1e5 a method keeps).

Writes ``stability.md`` and ``stability.json`` in the report folder (``make eval`` summarises
the latter) and prints the table.
"""
from __future__ import annotations

import datetime
import time
from pathlib import Path
from typing import Callable

import numpy as np

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.progress import progress

from .harness import run_method
from .methods import Loader, MethodUnavailable, check_names
from .report import fmt_seconds, markdown_table, write_json, write_text

BASE = (64, 64)          # (H, W) of the cases that are not about size
_SPLIT = {"diffuse_direct": 0.4, "specular_direct": 0.1, "diffuse_indirect": 0.4, "specular_indirect": 0.1}


def synthetic_buffers(h: int, w: int, seed: int = 0, level: float = 0.5, noise: float = 0.7, spp: int = 4,
                      phase: float = 0.0) -> dict[str, np.ndarray]:
    """A plausible noisy frame: every schema buffer and its variance, (H, W, C) float32.

    Colour is a smooth pattern (shifted by ``phase``) times ``1 + noise·N(0, 1)`` (clamped at 0;
    ``noise=0`` gives the noise-free pattern); the five radiance components split it exactly
    (emission 0), so ``color`` equals their sum as the renderer guarantees. Variances are those of
    the pixel mean, i.e. ``(noise·truth)²``.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    yy, xx = yy / max(h, 1), xx / max(w, 1)
    truth = level * np.stack([0.6 + 0.4 * np.sin(6 * xx + phase), 0.6 + 0.4 * np.cos(5 * yy + 2 * phase),
                              0.5 + 0.3 * np.sin(4 * (xx + yy) + phase)], -1)
    color = np.maximum(truth * (1 + noise * rng.standard_normal(truth.shape)), 0)
    normal = np.stack([np.sin(3 * xx + phase), np.cos(3 * yy), np.ones_like(xx)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    out = {"color": color, "emission": np.zeros_like(color),
           **{k: f * color for k, f in _SPLIT.items()},
           "albedo": np.clip(0.3 + 0.5 * truth / max(level, 1e-12), 0, 1), "normal": normal,
           "depth": (1.0 + 2.0 * xx)[..., None], "roughness": np.full((h, w, 1), 0.5),
           "metallic": np.zeros((h, w, 1)), "transmission": np.zeros((h, w, 1))}
    var_color = (noise * truth) ** 2
    for b in schema.BUFFERS:
        if b.radiance:
            v = var_color * (1.0 if b.name == "color" else _SPLIT.get(b.name, 0.0) ** 2)
        else:
            v = np.full(out[b.name].shape, 1e-4 / spp)
        out[schema.variance_name(b.name)] = v
    return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}


def _set_radiance(buf: dict, color: np.ndarray, variance: np.ndarray) -> dict:
    buf["color"] = color.astype(np.float32)
    buf[schema.variance_name("color")] = variance.astype(np.float32)
    buf["emission"] = np.zeros_like(buf["color"])
    for k, f in _SPLIT.items():
        buf[k] = (f * color).astype(np.float32)
        buf[schema.variance_name(k)] = (f * f * variance).astype(np.float32)
    return buf


def _fireflies() -> dict:
    b = synthetic_buffers(*BASE, seed=1, level=0.01)
    rng = np.random.default_rng(11)
    mask = rng.random(BASE) < 0.005
    mask[BASE[0] // 2, BASE[1] // 2] = True
    color, var = b["color"].copy(), b["color.variance"].copy()
    color[mask] = 1e4
    var[mask] = 1e8 / 4
    return _set_radiance(b, color, var)


def _black() -> dict:
    b = synthetic_buffers(*BASE, seed=2)
    z = np.zeros_like(b["color"])
    return _set_radiance(b, z, z)


def _bright() -> dict:
    b = synthetic_buffers(*BASE, seed=3)
    return _set_radiance(b, np.full_like(b["color"], 1e5), np.full_like(b["color"], 1e8))


def _nan_inf() -> dict:
    b = synthetic_buffers(*BASE, seed=4)
    rng = np.random.default_rng(14)
    for key, frac in (("color", 0.02), ("diffuse_indirect", 0.01), ("albedo", 0.01), ("normal", 0.01),
                      ("depth", 0.01), ("color.variance", 0.01)):
        a = b[key]
        m = rng.random(a.shape[:2]) < frac
        a[m] = np.nan
        m = rng.random(a.shape[:2]) < frac / 2
        a[m] = np.inf
        m = rng.random(a.shape[:2]) < frac / 2
        a[m] = -np.inf
    return b


def _zero_albedo() -> dict:
    b = synthetic_buffers(*BASE, seed=5)
    b["albedo"][:] = 0
    b["albedo.variance"][:] = 0
    return b


def _bad_normals() -> dict:
    b = synthetic_buffers(*BASE, seed=6)
    rng = np.random.default_rng(16)
    n = b["normal"]
    n[: BASE[0] // 2] = 0.0                                             # zero length
    n[BASE[0] // 2:] = (rng.standard_normal(n[BASE[0] // 2:].shape) * 1e3).astype(np.float32)  # garbage
    return b


CASES: dict[str, tuple[str, Callable[[], dict]]] = {
    "fireflies_1e4": ("dark frame (0.01) with 0.5 % pixels at 1e4", _fireflies),
    "all_black": ("radiance and variance 0 everywhere", _black),
    "radiance_1e5": ("radiance 1e5 everywhere", _bright),
    "nan_inf": ("NaN/+Inf/-Inf in colour, a component, albedo, normal, depth, variance", _nan_inf),
    "zero_albedo": ("albedo 0 everywhere", _zero_albedo),
    "bad_normals": ("zero-length normals (top half), garbage |n| ~ 1e3 (bottom half)", _bad_normals),
    "size_8x8": ("8 x 8 pixels", lambda: synthetic_buffers(8, 8, seed=7)),
    "size_64x24": ("non-square 64 wide x 24 high", lambda: synthetic_buffers(24, 64, seed=8)),
    "size_33x17": ("odd 33 wide x 17 high", lambda: synthetic_buffers(17, 33, seed=9)),
    "size_1920x1080": ("full HD 1920 x 1080 (tiled where the method tiles)", lambda: synthetic_buffers(1080, 1920,
                                                                                                     seed=10)),
}
LARGE = ("size_1920x1080",)


def run_stability(cfg: Config, large: bool | None = None, out: str | Path | None = None,
                  quiet: bool = False) -> dict:
    from .run import report_dir

    t0 = time.perf_counter()
    e = cfg.eval
    check_names(e.methods)
    large = e.stability_large if large is None else large
    spp = int(e.spp[0]) if e.spp else 4
    loader = Loader(cfg)
    methods, unavailable = {}, {}
    for name in e.methods:
        try:
            methods[name] = loader.load(name, spp)
        except MethodUnavailable as exc:
            unavailable[name] = str(exc)
    cases = [c for c in CASES if large or c not in LARGE]
    results: dict[str, dict] = {}
    repaired: dict[str, int] = {}
    input_mean: dict[str, float] = {}
    bar = progress(total=len(cases) * max(1, len(methods)), desc="stability", unit="run", disable=quiet)
    for case in cases:
        buffers = CASES[case][1]()
        c = buffers["color"]
        input_mean[case] = float(c[np.isfinite(c)].mean())
        row = {}
        for name in e.methods:
            if name not in methods:
                row[name] = {"status": "not available"}
                continue
            oc = run_method(methods[name], buffers)
            repaired[case] = int(sum(oc.input_repaired.values()))
            cell = {"status": oc.status(), "seconds": oc.seconds, **({"note": oc.note} if oc.note else {})}
            if oc.output is not None:
                fin = oc.output[np.isfinite(oc.output)]
                cell.update(shape=list(oc.output.shape), out_min=float(fin.min()) if fin.size else None,
                            out_max=float(fin.max()) if fin.size else None,
                            out_mean=float(fin.mean()) if fin.size else None)
            row[name] = cell
            bar.update(1)
        results[case] = row
    bar.close()
    data = {"date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"), "spp": spp,
            "cases": {c: CASES[c][0] for c in cases}, "input_repaired": repaired, "input_mean": input_mean,
            "results": results,
            "unavailable": unavailable, "seconds": time.perf_counter() - t0}
    out_dir = Path(out) if out else report_dir(cfg)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "stability.json", data)
    text = format_markdown(data, list(e.methods))
    write_text(out_dir / "stability.md", text)
    if not quiet:
        print(text)
    ran = [c for r in results.values() for c in r.values() if c["status"] != "not available"]
    failed = sum(c["status"] != "ok" for c in ran)
    print(f"stability: {len(cases)} cases x {len(methods)} methods: {len(ran) - failed} ok, {failed} failed, "
          f"{len(unavailable)} method(s) not available, {data['seconds']:.1f} s -> {out_dir}/stability.md", flush=True)
    return data


def format_markdown(data: dict, methods: list[str]) -> str:
    def cell(c: dict) -> str:
        if c["status"] == "not available":
            return "n/a"
        if c["status"] == "ok":
            note = f" ({c['note']})" if c.get("note") else ""
            return f"ok {fmt_seconds(c['seconds'])} s, mean {c['out_mean']:.3g}{note}"
        return f"**FAIL** {c['status'][:160]} ({fmt_seconds(c['seconds'])} s)"

    rows = [[f"{case}: {desc}", f"{data['input_mean'][case]:.3g}", str(data["input_repaired"].get(case, 0))]
            + [cell(data["results"][case][m]) for m in methods] for case, desc in data["cases"].items()]
    lines = ["# Stability", "",
             f"{data['date']}, checkpoints of {data['spp']} spp. A run passes (ok) when the method returns a finite "
             "(H, W, 3) image; times are denoise wall seconds, 'mean' the output's mean radiance (compare the "
             "input mean). 'NaN/Inf repaired' counts the input values set to 0 before any method saw them.", ""]
    lines += markdown_table(["case", "input mean", "NaN/Inf repaired", *[f"`{m}`" for m in methods]], rows)
    if data["unavailable"]:
        lines += ["", "Not available:"] + [f"- `{m}`: {why}" for m, why in data["unavailable"].items()]
    return "\n".join(lines) + "\n"
