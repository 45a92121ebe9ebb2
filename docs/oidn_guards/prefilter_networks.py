"""OIDN's clean-aux networks on prefiltered aux against `oidn`: the large one (what quality high runs), the
regular one as custom weights, and quality balanced; every noise realization of a store split.

    python docs/oidn_guards/prefilter_networks.py STORE SPLIT [PREFIX]
"""
import sys

import numpy as np

from mcdenoise.evaluate.run import realization_stacks
from mcdenoise.pipeline.metrics import psnr
from mcdenoise.pipeline.store import Store
from mcdenoise.train import oidn


def main(store_path, split, prefix=""):
    regular = oidn.weights_blob("rt_hdr_calb_cnrm")
    store = Store(store_path)
    keys = sorted((k for k in store.frames(split) if k.scene.startswith(prefix)), key=str)
    for spp in (4, 16):
        rows = []
        for key in keys:
            ref_name = "gt_clean" if store.image_path(key.scene, key.frame, "gt_clean").exists() else "gt1"
            ref = store.read_image(key.scene, key.frame, ref_name, ["color"])[0]["color"]
            d = []
            for stacks in realization_stacks(store, key, spp, n=1 << 30):
                b = store.read(key.scene, key.frame, spp, stacks=stacks)
                p0 = psnr(oidn.denoise(b), ref)
                d.append([psnr(oidn.denoise(b, clean_aux=True), ref) - p0,
                          psnr(oidn.denoise(b, clean_aux=True, weights=regular), ref) - p0,
                          psnr(oidn.denoise(b, clean_aux=True, quality="balanced"), ref) - p0])
            rows.append(np.mean(d, 0))
            print(f"{spp:3d} {str(key):32s} large {rows[-1][0]:+.3f} regular {rows[-1][1]:+.3f} "
                  f"balanced {rows[-1][2]:+.3f}", flush=True)
        m = np.mean(rows, 0)
        print(f"{spp:3d} MEAN large {m[0]:+.3f} regular {m[1]:+.3f} balanced {m[2]:+.3f}  worst {np.min(rows, 0)}")


if __name__ == "__main__":
    main(*sys.argv[1:])
