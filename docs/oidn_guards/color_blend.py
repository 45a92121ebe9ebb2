"""The shipped colour-only `oidn_ft` weights at other blends, against stock colour-only OIDN.

`train/shipped/oidn_ft/rt_hdr.tza` is OIDN's colour-only network fine-tuned on the ship data and
blended halfway back (w = w_oidn + 0.5 (w_ft − w_oidn)); any blend b ≤ 0.5 is
w_oidn + (b / 0.5) (w_shipped − w_oidn). Each blend runs in OIDN itself (pyoidn with the weights, as
`denoise --exr` runs it on an R,G,B-only EXR) on every noise realization of every frame, PSNR as
`make eval` computes it (against GT_clean where the frame has one, else GT1).

    python docs/oidn_guards/color_blend.py --store data/external --split external --prefix ext_val \
        --blends 0.5 0.4 0.3 0.2 --spp 4 16 --json out.json
"""
import argparse
import json
import sys

import numpy as np

from mcdenoise.evaluate.run import realization_stacks
from mcdenoise.pipeline import oidn, oidn_weights, tza
from mcdenoise.pipeline.metrics import psnr
from mcdenoise.pipeline.store import Store
from mcdenoise.train.model import SHIPPED_MODEL

SHIPPED_BLEND = 0.5


def blob_at(blend: float) -> bytes:
    """The shipped colour-only weights moved to ``blend`` (0: stock OIDN's rt_hdr)."""
    stock = tza.read(oidn_weights.load("rt_hdr"), "rt_hdr")
    shipped = tza.read((SHIPPED_MODEL / "oidn_ft" / "rt_hdr.tza").read_bytes(), "shipped rt_hdr")
    t = blend / SHIPPED_BLEND
    def moved(k):
        a, b = stock[k].array.astype(np.float64), shipped[k].array.astype(np.float64)
        return tza.Tensor((a + t * (b - a)).astype(stock[k].array.dtype), stock[k].layout)
    return tza.write({k: moved(k) for k in stock})


def gains(store: Store, key, spp: int, blobs: dict) -> dict:
    """{blend: [PSNR(blend) − PSNR(stock colour-only OIDN) on each realization]}."""
    ref_name = "gt_clean" if store.image_path(key.scene, key.frame, "gt_clean").exists() else "gt1"
    ref = store.read_image(key.scene, key.frame, ref_name, ["color"])[0]["color"]
    out = {b: [] for b in blobs}
    for stacks in realization_stacks(store, key, spp, n=1 << 30):
        buffers = store.read(key.scene, key.frame, spp, stacks=stacks)
        stock = psnr(oidn.denoise(buffers, aux=False), ref)
        for b, blob in blobs.items():
            out[b].append(psnr(oidn.denoise(buffers, aux=False, weights=blob), ref) - stock)
    return out


def main(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("--store", default="data/external")
    ap.add_argument("--split", default="external")
    ap.add_argument("--prefix", default="")
    ap.add_argument("--exclude", default="")
    ap.add_argument("--blends", nargs="+", type=float, default=[0.5, 0.4, 0.3, 0.2])
    ap.add_argument("--spp", nargs="+", type=int, default=[4, 16])
    ap.add_argument("--json", default="")
    a = ap.parse_args(argv)
    store = Store(a.store)
    keys = sorted((k for k in store.frames(a.split) if k.scene.startswith(a.prefix)
                   and not (a.exclude and k.scene.startswith(a.exclude))), key=str)
    blobs = {b: blob_at(b) for b in a.blends}
    result = {}
    for spp in a.spp:
        result[spp] = {str(k): gains(store, k, spp, blobs) for k in keys}
        print(f"{spp} spp, {len(keys)} frames: mean over each frame's realizations of PSNR − stock colour-only OIDN, dB")
        for b in a.blends:
            per = {k: float(np.mean(v[b])) for k, v in result[spp].items()}
            worst = min(per, key=per.get)
            print(f"  blend {b:.2f}: mean {np.mean(list(per.values())):+.3f}, worst {per[worst]:+.3f} ({worst}); "
                  + " ".join(f"{k.split('/')[0]}:{v:+.2f}" for k, v in per.items()))
    if a.json:
        with open(a.json, "w") as f:
            json.dump({str(s): {k: {str(b): g for b, g in v.items()} for k, v in r.items()} for s, r in result.items()},
                      f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
