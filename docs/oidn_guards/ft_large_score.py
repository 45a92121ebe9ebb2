"""Probe: the large clean-aux oidn_ft run (ft_large.py), exported to OIDN and run in its final-frame mode, at
blends b, against oidn_prefilter on every realization of a store split.

    python docs/oidn_guards/ft_large_score.py RUN_FOLDER STORE SPLIT PREFIX 4[,16] 1.0,0.5
"""
import dataclasses
import sys

import numpy as np

from mcdenoise.evaluate.run import realization_stacks
from mcdenoise.pipeline import oidn
from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.metrics import psnr
from mcdenoise.pipeline.store import Store
from mcdenoise.train import oidn_ft

run, store_path, split, prefix, spps = sys.argv[1:6]
blends = [float(b) for b in sys.argv[6].split(",")]
cfg = load_config("configs/default.yaml", [])
cfg = dataclasses.replace(cfg, oidn_ft=dataclasses.replace(cfg.oidn_ft, network="rt_hdr_calb_cnrm_large"))
blobs = {b: oidn_ft.export_blob(oidn_ft.load_run(run, cfg, blend=b)[0]) for b in blends}
store = Store(store_path)
keys = sorted((k for k in store.frames(split) if k.scene.startswith(prefix)), key=str)
for spp in [int(s) for s in spps.split(",")]:
    rows = []
    for key in keys:
        ref_name = "gt_clean" if store.image_path(key.scene, key.frame, "gt_clean").exists() else "gt1"
        ref = store.read_image(key.scene, key.frame, ref_name, ["color"])[0]["color"]
        d = []
        for stacks in realization_stacks(store, key, spp, n=1 << 30):
            b = store.read(key.scene, key.frame, spp, stacks=stacks)
            p0 = psnr(oidn.denoise(b, clean_aux=True), ref)
            d.append([psnr(oidn.denoise(b, clean_aux=True, weights=blobs[x]), ref) - p0 for x in blends])
        rows.append(np.mean(d, 0))
        print(f"{spp:3d} {str(key):30s} " + "  ".join(f"b{x:g} {v:+.3f}" for x, v in zip(blends, rows[-1])), flush=True)
    m, w = np.mean(rows, 0), np.min(rows, 0)
    print(f"{spp:3d} MEAN " + "  ".join(f"b{x:g} {v:+.3f} (worst {u:+.3f})" for x, v, u in zip(blends, m, w)), flush=True)
