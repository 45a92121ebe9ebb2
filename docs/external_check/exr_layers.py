"""`denoise --exr` on EXRs with fewer layers: R,G,B only, and R,G,B + albedo + normal (no variances),
written from external scenes of the store at one spp, each against stock OIDN on the same layers
(PSNR against GT1). Run from the repository root:
``.venv/bin/python docs/external_check/exr_layers.py cornell_variant,night_street [--spp 4]``.
"""
import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenEXR

from mcdenoise.pipeline import schema
from mcdenoise.pipeline.exr import read_image
from mcdenoise.pipeline.metrics import psnr
from mcdenoise.pipeline.store import Store

CHANNELS = {b.name: b.exr_channels for b in schema.BUFFERS}


def write_layers(path: Path, buffers: dict, layers: list[str]) -> None:
    pixels = {c: np.ascontiguousarray(buffers[name][..., i].astype(np.float32))
              for name in layers for i, c in enumerate(CHANNELS[name])}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, pixels) as f:
        f.write(str(path))


def denoised_psnr(src: Path, method: str, spp: int, ref: np.ndarray) -> float:
    out = src.with_name(f"{src.stem}_{method}.exr")
    cmd = [sys.executable, "-m", "mcdenoise", "denoise", "--exr", str(src), "--out", str(out), "--spp", str(spp),
           "--method", method]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(proc.stderr)
    return psnr(read_image(out)[0]["color"], ref)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--store", default="data/external")
    args = ap.parse_args()
    store, tmp = Store(args.store), Path(tempfile.mkdtemp())
    for name in args.scenes.split(","):
        key = next(k for k in store.frames("external") if k.scene == f"ext_{name}")
        buffers = store.read(key.scene, key.frame, args.spp)
        ref = store.read_image(key.scene, key.frame, "gt1", ["color"])[0]["color"]
        for layers in (["color"], ["color", "albedo", "normal"]):
            src = tmp / f"{name}_{len(layers)}.exr"
            write_layers(src, buffers, layers)
            ours, stock = (denoised_psnr(src, m, args.spp, ref) for m in ("ours", "oidn"))
            print(f"{name}, {'+'.join(layers)}: ours {ours:.2f} / oidn {stock:.2f} ({ours - stock:+.2f} dB)", flush=True)


if __name__ == "__main__":
    main()
