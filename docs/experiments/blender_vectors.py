"""Blender's Vector pass against ``pipeline.motion.flow``: is the convention right on a real Cycles render?

    python3.11 -m venv /tmp/bpy && /tmp/bpy/bin/pip install bpy==4.5.15       # Blender as a Python module
    /tmp/bpy/bin/python docs/experiments/blender_vectors_scene.py -- 8 /tmp/blend/frame_####
    /tmp/bpy/bin/python docs/experiments/blender_vectors_scene.py -- 4096 /tmp/blend/ref_####
    python docs/experiments/blender_vectors.py /tmp/blend

With the light passes (docs/sequences.md, "A Blender shot's light passes"), 8 frames at 4 and 16 spp:

    for spp in 4 16; do /tmp/bpy/bin/python docs/experiments/blender_vectors_scene.py -- --frames 8 $spp \
      /tmp/blend$spp/frame_####; done
    /tmp/bpy/bin/python docs/experiments/blender_vectors_scene.py -- --frames 8 --seed 1 4096 /tmp/blend4/ref_####
    python docs/experiments/blender_vectors.py --plain /tmp/blend4      # copies without the light passes: plain/
    d=/tmp/blend4; s="denoise --sequence"
    python -m pipeline $s "$d/plain/frame_####.exr" --out "$d/o_oidn_perframe/####.exr" --method oidn_prefilter \
      --temporal-weight 1 --temporal-window 1 --ahead 0
    python -m pipeline $s "$d/plain/frame_####.exr" --out "$d/o_plain_defaults/####.exr"
    python -m pipeline $s "$d/frame_####.exr" --out "$d/o_light_perframe/####.exr" --temporal-weight 1 \
      --temporal-window 1 --ahead 0
    python -m pipeline $s "$d/frame_####.exr" --out "$d/o_light_before/####.exr" --ahead 0
    python -m pipeline $s "$d/frame_####.exr" --out "$d/o_light_defaults/####.exr"
    python docs/experiments/blender_vectors.py /tmp/blend4

(the same for 16 spp, with ref_* copied into /tmp/blend16).

Warps frame t-1's Denoising Albedo (noise-free up to anti-aliasing) into frame t with the flow read three ways
(``from_blender_vectors``, y not flipped, all negated) and prints the PSNR against frame t's albedo on the valid
pixels, beside the unwarped PSNR. With the 4096 spp references it also prints the denoisers' PSNR per frame, per
frame and with the temporal filter, from ``denoise --sequence`` outputs in <folder>/o_<method>_<weight>/.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mcdenoise.pipeline import motion
from mcdenoise.pipeline.exr import read_layers
from mcdenoise.pipeline.metrics import psnr


def flat_psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def vector(path: Path) -> np.ndarray:
    passes: dict = {}
    read_layers(path, passes=passes)
    return passes["Vector"]


def plain(folder: Path) -> None:
    """Copies of ``folder``'s frame_*.exr without Cycles' light passes, in ``folder``/plain."""
    import OpenEXR

    from mcdenoise.pipeline.exr import CYCLES_LOBES
    light = {name for roles in CYCLES_LOBES.values() for spellings in roles for name in spellings}
    (folder / "plain").mkdir(exist_ok=True)
    for path in sorted(folder.glob("frame_*.exr")):
        with OpenEXR.File(str(path), separate_channels=True) as f:
            kept = {n: c.pixels for n, c in f.channels().items() if n.split(".")[-2] not in light}
            stamps = {k: v for k, v in f.header().items() if isinstance(v, str)}     # Cycles' sample count among them
        with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **stamps},
                          kept) as f:
            f.write(str(folder / "plain" / path.name))


def main(folder: Path) -> int:
    frames = sorted(folder.glob("frame_*.exr"))
    readings = {"from_blender_vectors": motion.from_blender_vectors,
                "y not flipped": lambda v: np.stack([v[..., 0], v[..., 1], -v[..., 2], -v[..., 3]], -1),
                "negated": lambda v: -motion.from_blender_vectors(v)}
    for prev, cur in zip(frames, frames[1:]):
        a_prev, a_cur = read_layers(prev)["albedo"], read_layers(cur)["albedo"]
        cells = [f"unwarped {flat_psnr(a_prev, a_cur):.1f} dB"]
        for name, read in readings.items():
            xy, valid = motion.flow(read(vector(cur)), read(vector(prev)))
            warped = motion.warp(a_prev, xy, valid)
            cells.append(f"{name}: {flat_psnr(warped[valid], a_cur[valid]):.1f} dB on {100 * valid.mean():.0f} %")
        print(f"{cur.name}: " + "; ".join(cells))
    refs = sorted(folder.glob("ref_*.exr"))
    for out in sorted(folder.glob("o_*_*")):
        if refs:
            values = [psnr(read_layers(out / r.name.removeprefix("ref_"))["color"], read_layers(r)["color"]) for r in refs]
            print(f"{out.name}: " + " ".join(f"{v:.2f}" for v in values) + f"; frames 2-: {np.mean(values[1:]):.2f} dB")
    return 0


if __name__ == "__main__":
    if sys.argv[1] == "--plain":
        raise SystemExit(plain(Path(sys.argv[2])))
    raise SystemExit(main(Path(sys.argv[1])))
