"""Probe: the shipped Control Module's correction (ours − base_only, in OIDN's PU space) added to OIDN's
prefiltered-aux output (candidate T of realizations/prefilter/RULE.md). Every realization; − oidn_prefilter, dB.

    python docs/oidn_guards/transplant_probe.py STORE SPLIT PREFIX 4[,16]
"""
import sys

import numpy as np
import torch

from mcdenoise.evaluate.methods import Loader
from mcdenoise.evaluate.run import realization_stacks
from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.metrics import psnr
from mcdenoise.pipeline.store import Store
from mcdenoise.train import oidn
from mcdenoise.train.model import autoexposure, from_pu, to_pu


def pu(x, s):
    return to_pu(torch.from_numpy(np.maximum(x, 0) * s))


def gains(store, key, spp, ours, base):
    """[T, ours, oidn] − oidn_prefilter, dB, averaged over the frame's realizations."""
    ref_name = "gt_clean" if store.image_path(key.scene, key.frame, "gt_clean").exists() else "gt1"
    ref = store.read_image(key.scene, key.frame, ref_name, ["color"])[0]["color"]
    out = []
    for stacks in realization_stacks(store, key, spp, n=1 << 30):
        b = store.read(key.scene, key.frame, spp, stacks=stacks)
        s = autoexposure(b["color"])
        ours.set_frame(store, key)
        o = np.asarray(ours.denoise(b), np.float32)
        base.set_frame(store, key)
        bo = np.asarray(base.denoise(b), np.float32)
        pre = oidn.denoise(b, clean_aux=True)
        t = (from_pu((pu(pre, s) + pu(o, s) - pu(bo, s)).clamp(min=0)) / s).numpy()
        p0 = psnr(pre, ref)
        out.append([psnr(t, ref) - p0, psnr(o, ref) - p0, psnr(oidn.denoise(b), ref) - p0])
    return np.mean(out, 0)


def main(store_path, split, prefix, spps):
    store = Store(store_path)
    keys = sorted((k for k in store.frames(split) if k.scene.startswith(prefix)), key=str)
    loader = Loader(load_config("configs/default.yaml", ["runs=/tmp/norun"]))
    for spp in [int(x) for x in spps.split(",")]:
        ours, base = loader.load("ours", spp), loader.load("base_only", spp)
        rows = []
        for key in keys:
            rows.append(gains(store, key, spp, ours, base))
            print(f"{spp:3d} {str(key):30s} transplant {rows[-1][0]:+.3f}  ours {rows[-1][1]:+.3f}  "
                  f"oidn {rows[-1][2]:+.3f}", flush=True)
        m, w = np.mean(rows, 0), np.min(rows, 0)
        print(f"{spp:3d} MEAN transplant {m[0]:+.3f}  ours {m[1]:+.3f}  oidn {m[2]:+.3f}   WORST transplant {w[0]:+.3f}")


if __name__ == "__main__":
    main(*sys.argv[1:])
