"""A contact sheet of random scenes: interiors, product shots and the open sets of the default config,
rendered small with the pipeline's integrator into one labelled PNG grid (``pipeline.figures.contact_sheet``,
each tile exposed by itself), with the build and render seconds per frame of each kind (docs/scenes.md shows
both).

    python -m tools.contact_sheet [--out docs/figures/scenes.png] [--interiors 160] [--products 80] [--objects 60]
                                  [--res 64] [--spp 32]

(``make contact-sheet``.) Scenes come from configs/default.yaml's scene section with only the kind's
probability set to 1, seed 0, frame 0 of a 2-frame move.
"""
from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import time
from pathlib import Path

import numpy as np

KINDS = ("interior", "product", "objects")
COLS = 20


def render_kind(mi, scene_cfg, kind: str, count: int, res: int, spp: int) -> tuple[list, list]:
    """(labelled HDR colour images, [build s, render s] per frame) of ``count`` scenes of one kind."""
    from mcdenoise.render.buffers import render_image
    from mcdenoise.render.scene import build_scene, build_sensor, random_scene

    cfg = dataclasses.replace(scene_cfg, interior_probability=float(kind == "interior"),
                              product_probability=float(kind == "product"))
    cells, times = [], []
    for index in range(count):
        desc = random_scene(cfg, 0, index, 2)
        t0 = time.perf_counter()
        scene = build_scene(mi, desc)
        t1 = time.perf_counter()
        result = render_image(mi, scene, build_sensor(mi, desc, 0, res, res), spp=spp, seed=index, features=set())
        times.append([t1 - t0, time.perf_counter() - t1])
        cells.append((f"{kind} {index}", result.buffers["color"]))
        del scene
        gc.collect()
        print(f"{kind} {index}: build {times[-1][0]:.2f} s, render {times[-1][1]:.2f} s", flush=True)
    return cells, times


def kind_summary(times: list) -> dict:
    """Frames, mean build and render seconds and the first frame's seconds of one kind. The first frame
    compiles the kernels: the means leave it out (None with no other frame)."""
    a = np.asarray(times, dtype=np.float64).reshape(-1, 2)
    rest = a[1:]
    return {"frames": len(a),
            "build_s": round(float(rest[:, 0].mean()), 3) if len(rest) else None,
            "render_s": round(float(rest[:, 1].mean()), 3) if len(rest) else None,
            "first_frame_s": round(float(a[0].sum()), 3) if len(a) else None}


def main(argv=None) -> None:
    from mcdenoise.pipeline.config import load_config
    from mcdenoise.pipeline.exr import atomic_write_json
    from mcdenoise.pipeline.figures import contact_sheet
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/figures/scenes.png")
    ap.add_argument("--interiors", type=int, default=160)
    ap.add_argument("--products", type=int, default=80)
    ap.add_argument("--objects", type=int, default=60)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=32)
    args = ap.parse_args(argv)
    counts = (args.interiors, args.products, args.objects)
    if min(counts) < 0 or sum(counts) == 0:
        ap.error(f"--interiors {args.interiors} --products {args.products} --objects {args.objects}: "
                 "expected counts of 0 or more, at least one scene in all")
    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "default.yaml")
    mi = import_mitsuba(cfg.render.variant, cfg.render.threads)
    cells, summary = [], {}
    for kind, count in zip(KINDS, counts):
        c, times = render_kind(mi, cfg.scene, kind, count, args.res, args.spp)
        cells += c
        summary[kind] = kind_summary(times)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    contact_sheet(cells, out, cols=min(COLS, len(cells)), exposure=True, cell=1.0,
                  title=f"random scenes, frame 0, {args.res}x{args.res} at {args.spp} spp, each exposed by itself")
    summary["settings"] = {"resolution": args.res, "spp": args.spp, "variant": mi.variant()}
    atomic_write_json(out.with_suffix(".json"), summary)
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
