"""Probe: the large clean-aux oidn_ft run (ft_large_probe.py), exported to OIDN and run in its final-frame mode,
at blends b, against oidn_prefilter on every realization of a store split.

    python docs/oidn_guards/ft_large_score.py RUN_FOLDER STORE SPLIT PREFIX 4[,16] 1.0,0.5
"""
import dataclasses
import sys

import numpy as np
from realizations import realization_psnrs

from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.store import Store
from mcdenoise.train import oidn
from mcdenoise.train.baselines import oidn_ft


class Clean:
    """OIDN's final-frame mode with the given weights (None: its own)."""

    def __init__(self, blob=None):
        self.blob = blob

    def set_frame(self, store, key):
        pass

    def denoise(self, buffers):
        return oidn.denoise(buffers, clean_aux=True, weights=self.blob)


def main(run, store_path, split, prefix, spps, blend_list):
    blends = [float(b) for b in blend_list.split(",")]
    cfg = load_config("configs/default.yaml", [])
    cfg = dataclasses.replace(cfg, oidn_ft=dataclasses.replace(cfg.oidn_ft, network="rt_hdr_calb_cnrm_large"))
    methods = {"oidn_prefilter": Clean(), **{b: Clean(oidn_ft.export_blob(oidn_ft.load_run(run, cfg, blend=b)[0]))
                                            for b in blends}}
    store = Store(store_path)
    keys = sorted((k for k in store.frames(split) if k.scene.startswith(prefix)), key=str)
    for spp in [int(s) for s in spps.split(",")]:
        rows = []
        for key in keys:
            r = realization_psnrs(methods, store, key, spp)
            rows.append([np.mean(np.subtract(r[b], r["oidn_prefilter"])) for b in blends])
            print(f"{spp:3d} {str(key):30s} " + "  ".join(f"b{x:g} {v:+.3f}" for x, v in zip(blends, rows[-1])),
                  flush=True)
        m, w = np.mean(rows, 0), np.min(rows, 0)
        print(f"{spp:3d} MEAN " + "  ".join(f"b{x:g} {v:+.3f} (worst {u:+.3f})" for x, v, u in zip(blends, m, w)))


if __name__ == "__main__":
    main(*sys.argv[1:])
