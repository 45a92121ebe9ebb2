"""A contact sheet of random scenes: interiors, product shots and today's open sets, rendered small with the
pipeline's integrator and tonemapped into one PNG grid, with the build and render seconds per frame of each
kind (docs/scenes.md shows both).

    python -m tools.contact_sheet [--out docs/figures/scenes.png] [--interiors 80] [--products 48] [--objects 32]
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


def tonemap(rgb: np.ndarray) -> np.ndarray:
    """Linear radiance → 8-bit sRGB, exposed so the frame's mean luminance lands near mid-grey (Reinhard)."""
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    x = rgb * (0.18 / max(float(np.exp(np.mean(np.log(lum + 1e-4)))), 1e-4))
    x = x / (1.0 + x)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.clip(x, 0, 1), 1 / 2.4) - 0.055)
    return (np.clip(srgb, 0, 1) * 255 + 0.5).astype(np.uint8)


def grid(tiles: list, cols: int) -> np.ndarray:
    h, w, _ = tiles[0].shape
    rows = -(-len(tiles) // cols)
    out = np.zeros((rows * (h + 2), cols * (w + 2), 3), np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        out[r * (h + 2) + 1:r * (h + 2) + 1 + h, c * (w + 2) + 1:c * (w + 2) + 1 + w] = t
    return out


def render_kind(mi, scene_cfg, kind: str, count: int, res: int, spp: int) -> tuple[list, list]:
    """(tonemapped tiles, [build s, render s] per frame) of ``count`` scenes of one kind."""
    from mcdenoise.render.buffers import render_image
    from mcdenoise.render.scene import build_scene, build_sensor, random_scene

    cfg = dataclasses.replace(scene_cfg, interior_probability=float(kind == "interior"),
                              product_probability=float(kind == "product"))
    tiles, times = [], []
    for index in range(count):
        desc = random_scene(cfg, 0, index, 2)
        t0 = time.perf_counter()
        scene = build_scene(mi, desc)
        t1 = time.perf_counter()
        result = render_image(mi, scene, build_sensor(mi, desc, 0, res, res), spp=spp, seed=index, features=set())
        times.append([t1 - t0, time.perf_counter() - t1])
        tiles.append(tonemap(result.buffers["color"]))
        del scene
        gc.collect()
        print(f"{kind} {index}: build {times[-1][0]:.2f} s, render {times[-1][1]:.2f} s", flush=True)
    return tiles, times


def main(argv=None) -> None:
    from PIL import Image

    from mcdenoise.pipeline.config import load_config
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/figures/scenes.png")
    ap.add_argument("--interiors", type=int, default=80)
    ap.add_argument("--products", type=int, default=48)
    ap.add_argument("--objects", type=int, default=32)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=32)
    args = ap.parse_args(argv)
    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "default.yaml")
    mi = import_mitsuba(cfg.render.variant, cfg.render.threads)
    tiles, summary = [], {}
    for kind, count in zip(KINDS, (args.interiors, args.products, args.objects)):
        t, times = render_kind(mi, cfg.scene, kind, count, args.res, args.spp)
        tiles += t
        a = np.asarray(times)
        # the first frame of a kind compiles its kernels: left out of the means
        summary[kind] = {"frames": count, "build_s": round(float(a[1:, 0].mean()), 3),
                         "render_s": round(float(a[1:, 1].mean()), 3), "first_frame_s": round(float(a[0].sum()), 3)}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(grid(tiles, 20)).save(out, optimize=True)
    summary["settings"] = {"resolution": args.res, "spp": args.spp, "variant": mi.variant()}
    out.with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
