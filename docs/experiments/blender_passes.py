"""A shot as Blender's Cycles writes it, through ``denoise --sequence`` (docs/sequences.md, "A Blender shot's light
passes" has the rule this measures for).

    python docs/experiments/blender_passes.py --store data/val_seq --split external --spp 4,16

Per sequence of the split and per spp (the first noise realization), every frame is written as a Cycles multilayer
EXR under the view layer "ViewLayer": ``Noisy Image``, ``Denoising Albedo``, ``Denoising Normal`` and the ``Vector``
pass made from the store's cameras and depth as Cycles makes it (where the point was in the frame before and will be
in the frame after, occlusion not tested; 0 at the shot's two ends; the background far off screen), no depth, no
camera, no variance. ``plain`` files stop there; ``light`` files add the light passes: ``DiffDir``, ``DiffInd``
with ``DiffCol`` (the albedo where above 1e-3, else 1, the light divided by it), ``GlossDir``, ``GlossInd`` with
``GlossCol`` = 1, and ``Emit``. Then ``denoise --sequence`` (in this process) with train/shipped:

    plain        ours on the plain files, the defaults (what such a file gets without light passes)
    per_frame    ours on the light files, each frame alone (--temporal-window 1 --ahead 0 --temporal-weight 1)
    before       ours on the light files, --ahead 0 (the frames before, followed back along the vectors)
    both         ours on the light files, the defaults (the frames after too, followed forward)
    irr_before   as before, the light divided by the albedo averaged (``average_input(kind="irradiance")``)
    irr_both     as both, the light divided by the albedo averaged
    plain_z, both_z, irr_both_z   as plain, both, irr_both on files with Cycles' Depth pass (the store's depth): the
                 vectors' depth test (``motion.flow``)
    store        ours on the store's own buffers with their camera, depth and variances, the defaults

against ``oidn_prefilter`` per frame on the plain files. Prints per method and spp the mean over sequences of
(mean over t >= 1 of PSNR - oidn_prefilter's), with the sequences below it, and the seconds each run took.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import tempfile
import time
from pathlib import Path

import numpy as np
import OpenEXR
from history_clamp import oidn_sequences

from mcdenoise.evaluate.scoring import score
from mcdenoise.pipeline import motion
from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.exr import read_layers, write_image
from mcdenoise.train.sequence import cmd_denoise_sequence

RUNS = {"plain": ("plain", {}), "per_frame": ("light", {"window": 1, "ahead": 0, "weight": 1.0}),
        "before": ("light", {"ahead": 0, "kind": "diffuse"}), "both": ("light", {"kind": "diffuse"}),
        "irr_before": ("light", {"ahead": 0, "kind": "irradiance"}), "irr_both": ("light", {"kind": "irradiance"}),
        "store": ("store", {}),
        # the same files with Cycles' Depth pass: the vectors' depth test (motion.flow)
        "plain_z": ("plain_z", {}), "both_z": ("light_z", {"kind": "diffuse"}),
        "irr_both_z": ("light_z", {"kind": "irradiance"})}
OFF_SCREEN = 1e4        # a background pixel's vector: lands off screen, so it has no history


def cycles_vector(frames, t: int) -> np.ndarray:
    """Frame t's Vector pass as Cycles writes it (``motion.from_blender_vectors`` reads it back): (X, Y) = where
    the point was in frame t-1 minus where it is, (Z, W) = where it is minus where it will be, y up."""
    view = frames[t].views["input"]
    centres = motion.pixel_centres(view.camera.width, view.camera.height)
    halves = []
    for k in (t - 1, t + 1):
        if 0 <= k < len(frames):
            xy = motion.reproject(view.depth, view.camera, frames[k].views["input"].camera)[0] - centres
            halves.append(np.where(np.isfinite(xy), xy, OFF_SCREEN))
        else:
            halves.append(np.zeros(centres.shape))
    (px, py), (nx, ny) = (np.moveaxis(h, -1, 0) for h in halves)
    return np.stack([px, -py, -nx, ny], -1).astype(np.float32)


def write_cycles(path: Path, buffers: dict, vector: np.ndarray, light: bool, depth: bool = False) -> None:
    layers = {"Noisy Image": buffers["color"], "Denoising Albedo": buffers["albedo"], "Vector": vector}
    if depth:
        layers["Depth"] = buffers["depth"]
    if light:
        colour = np.where(buffers["albedo"] > 1e-3, buffers["albedo"], 1.0).astype(np.float64)
        layers.update({"DiffDir": buffers["diffuse_direct"] / colour, "DiffInd": buffers["diffuse_indirect"] / colour,
                       "DiffCol": colour, "GlossDir": buffers["specular_direct"],
                       "GlossInd": buffers["specular_indirect"], "GlossCol": np.ones_like(colour),
                       "Emit": buffers["emission"]})
    channels = {f"ViewLayer.{name}.{s}": np.ascontiguousarray(image[..., i], np.float32)
                for name, image in layers.items()
                for i, s in enumerate({"Vector": "XYZW", "Depth": "Z"}.get(name, "RGB"))}
    channels.update({f"ViewLayer.Denoising Normal.{s}": np.ascontiguousarray(buffers["normal"][..., i], np.float32)
                     for i, s in enumerate("XYZ")})
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(str(path))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True)
    ap.add_argument("--split", required=True)
    ap.add_argument("--spp", default="4,16")
    ap.add_argument("--model", default="train/shipped")
    ap.add_argument("--runs", default="plain,per_frame,before,both,store")
    ap.add_argument("--sequences", type=int, default=None, help="the first N sequences only (a quick look)")
    ap.add_argument("--depth-tolerance", type=float, default=None,
                    help="the vectors' depth test's tolerance (motion.FLOW_DEPTH_TOLERANCE) for every run")
    args = ap.parse_args()
    if args.depth_tolerance is not None:
        motion.FLOW_DEPTH_TOLERANCE = args.depth_tolerance
    from mcdenoise.pipeline.store import Store
    store, cfg, runs = Store(args.store), load_config(), args.runs.split(",")
    spps = [int(s) for s in args.spp.split(",")]
    gains = {r: {s: {} for s in spps} for r in runs}
    seconds = {r: 0.0 for r in runs}
    for spp in spps:
        for n, (name, frames, base) in enumerate(oidn_sequences(store, args.split, spp)):
            if args.sequences is not None and n >= args.sequences:
                break
            base_psnr = [score(y, f.reference, ["psnr"])["psnr"] for y, f in zip(base, frames)]
            with tempfile.TemporaryDirectory() as tmp:
                tmp = Path(tmp)
                for kind in ("plain", "light", "store", "plain_z", "light_z"):
                    (tmp / kind).mkdir()
                for t, f in enumerate(frames):
                    vector = cycles_vector(frames, t)
                    for kind in ("plain", "light", "plain_z", "light_z"):
                        write_cycles(tmp / kind / f"{t:03d}.exr", f.buffers, vector, light=kind.startswith("light"),
                                     depth=kind.endswith("_z"))
                    write_image(tmp / "store" / f"{t:03d}.exr", f.buffers, camera=f.views["input"].camera)
                for run in runs:
                    kind, options = RUNS[run]
                    t0, said = time.perf_counter(), io.StringIO()
                    with contextlib.redirect_stdout(said):       # its summary line, printed for the first sequence
                        cmd_denoise_sequence(cfg, str(tmp / kind / "###.exr"), str(tmp / f"out_{run}" / "###.exr"), spp,
                                             quiet=True, model=Path(args.model), device="cpu", **options)
                    seconds[run] += time.perf_counter() - t0
                    if n == 0:
                        print(f"{run}: {said.getvalue().strip().splitlines()[-1]}", flush=True)
                    psnr = [score(read_layers(tmp / f"out_{run}" / f"{t:03d}.exr")["color"], f.reference, ["psnr"])["psnr"]
                            for t, f in enumerate(frames)]
                    gains[run][spp][name] = float(np.mean(np.subtract(psnr[1:], base_psnr[1:])))
            print(f"{spp} spp {name}: " + ", ".join(f"{r} {gains[r][spp][name]:+.3f}" for r in runs), flush=True)
    print(f"\n{args.store} {args.split}: {len(gains[runs[0]][spps[0]])} sequences, t >= 1, PSNR gain over "
          "oidn_prefilter per frame (mean over sequences; sequences below it)")
    print("| run | " + " | ".join(f"{s} spp" for s in spps) + " | mean | s |")
    print("| --- |" + " ---: |" * (len(spps) + 2))
    for r in runs:
        per = [float(np.mean(list(gains[r][s].values()))) for s in spps]
        below = [sum(v < 0 for v in gains[r][s].values()) for s in spps]
        print(f"| {r} | " + " | ".join(f"{p:+.3f} ({b})" for p, b in zip(per, below))
              + f" | {np.mean(per):+.3f} | {seconds[r]:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
