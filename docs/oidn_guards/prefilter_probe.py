"""OIDN's final-frame mode (aux prefiltered, cleanAux) and the shipped `ours`, with and without the
prefiltered aux in its input, against `oidn` on every noise realization of a store's frames.

`oidn_prefilter − oidn` alone is also `realizations.py --methods oidn_prefilter`; this adds what
`ours` does when its albedo and normal are the prefiltered ones (`ours+pre`).

    python docs/oidn_guards/prefilter_probe.py STORE SPLIT [PREFIX] [--spp 4 16] -- [overrides, e.g. runs=/tmp/norun]
"""
import argparse

import numpy as np

from mcdenoise.evaluate.methods import Loader
from mcdenoise.evaluate.run import realization_stacks
from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.metrics import psnr
from mcdenoise.pipeline.store import Store
from mcdenoise.train import oidn

COLUMNS = ("oidn_prefilter", "ours", "ours+pre")


def gains(store, key, spp, ours):
    """[oidn_prefilter, ours, ours+pre] − oidn, dB, averaged over the frame's realizations at ``spp``."""
    ref_name = "gt_clean" if store.image_path(key.scene, key.frame, "gt_clean").exists() else "gt1"
    ref = store.read_image(key.scene, key.frame, ref_name, ["color"])[0]["color"]
    out = []
    for stacks in realization_stacks(store, key, spp, n=1 << 30):
        b = store.read(key.scene, key.frame, spp, stacks=stacks)
        _, albedo, normal = oidn._inputs(b, True)
        albedo, normal = oidn.prefilter_aux(albedo, normal)
        ours.set_frame(store, key)
        mine = psnr(np.asarray(ours.denoise(b), np.float32), ref)
        ours.set_frame(store, key)
        mine_pre = psnr(np.asarray(ours.denoise({**b, "albedo": albedo, "normal": normal}), np.float32), ref)
        base = psnr(oidn.denoise(b), ref)
        out.append([psnr(oidn.denoise(b, clean_aux=True), ref) - base, mine - base, mine_pre - base])
    return np.mean(out, 0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("store")
    ap.add_argument("split")
    ap.add_argument("prefix", nargs="?", default="")
    ap.add_argument("--spp", nargs="+", type=int, default=[4])
    ap.add_argument("overrides", nargs="*")
    a = ap.parse_args()
    store, loader = Store(a.store), Loader(load_config("configs/default.yaml", a.overrides))
    keys = sorted((k for k in store.frames(a.split) if k.scene.startswith(a.prefix)), key=str)
    for spp in a.spp:
        ours = loader.load("ours", spp)
        rows = []
        for key in keys:
            rows.append(gains(store, key, spp, ours))
            print(f"{spp:3d} spp {str(key):32s} " + "  ".join(f"{c} {v:+.3f}" for c, v in zip(COLUMNS, rows[-1])),
                  flush=True)
        for what, v in (("mean", np.mean(rows, 0)), ("worst", np.min(rows, 0))):
            print(f"{spp:3d} spp {what:32s} " + "  ".join(f"{c} {x:+.3f}" for c, x in zip(COLUMNS, v)))


if __name__ == "__main__":
    main()
