"""Shipped (or any exported) `oidn_ft` weights at other blends, against stock OIDN on the same layers.

`train/shipped/oidn_ft/<network>.tza` is one of OIDN's networks fine-tuned on the ship data and blended
back toward OIDN (w = w_oidn + B (w_ft − w_oidn), B its `blend`, 0.5 for the shipped files); any blend
b ≤ B is w_oidn + (b / B) (w_file − w_oidn). Each blend runs in OIDN itself (pyoidn with the weights,
as `denoise --exr` runs it on an EXR with those layers) on every noise realization of every frame, PSNR
as `make eval` computes it (against GT_clean where the frame has one, else GT1).

    python docs/oidn_guards/ft_blend.py --store data/external --split external --prefix ext_val \
        --blends 0.5 0.4 0.3 0.2 --spp 4 16 --json out.json          # the shipped colour-only weights
    python docs/oidn_guards/ft_blend.py --network rt_hdr_alb --weights run_b1.tza --weights-blend 1 ...
"""
import argparse
import json
import sys

import numpy as np

from mcdenoise.evaluate.run import realization_stacks
from mcdenoise.pipeline.metrics import psnr
from mcdenoise.pipeline.store import Store
from mcdenoise.pipeline.weights import TZATensor, read_tza, write_tza
from mcdenoise.train import oidn
from mcdenoise.train.baselines.oidn_ft import blended
from mcdenoise.train.model import SHIPPED_MODEL, oidn_ft_blob


def blob_at(network: str, weights: bytes, weights_blend: float, blend: float) -> bytes:
    """``weights`` (exported at ``weights_blend``) moved to ``blend`` (0: stock OIDN's ``network``)."""
    stock = read_tza(oidn.weights_blob(network), network)
    given = read_tza(weights, f"{network} at blend {weights_blend}")
    f64 = lambda ts: {k: t.array.astype(np.float64) for k, t in ts.items()}  # noqa: E731
    moved = blended(f64(stock), f64(given), blend / weights_blend)
    return write_tza({k: TZATensor(moved[k].astype(t.array.dtype), t.layout) for k, t in stock.items()})


def gains(store: Store, key, spp: int, network: str, blobs: dict) -> dict:
    """{blend: [PSNR(blend) − PSNR(stock OIDN's ``network``) on each realization]}."""
    ref_name = "gt_clean" if store.image_path(key.scene, key.frame, "gt_clean").exists() else "gt1"
    ref = store.read_image(key.scene, key.frame, ref_name, ["color"])[0]["color"]
    out = {b: [] for b in blobs}
    for stacks in realization_stacks(store, key, spp, n=1 << 30):
        read = store.read(key.scene, key.frame, spp, stacks=stacks)
        buffers = {k: read[k] for k in ("color", *oidn.network_aux(network))}
        stock = psnr(oidn.denoise(buffers), ref)
        for b, blob in blobs.items():
            out[b].append(psnr(oidn.denoise(buffers, weights=blob), ref) - stock)
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
    ap.add_argument("--network", default="rt_hdr")
    ap.add_argument("--weights", default="", help="an exported .tza (default: the shipped one for --network)")
    ap.add_argument("--weights-blend", type=float, default=0.5, help="the blend --weights was exported at")
    a = ap.parse_args(argv)
    store = Store(a.store)
    keys = sorted((k for k in store.frames(a.split) if k.scene.startswith(a.prefix)
                   and not (a.exclude and k.scene.startswith(a.exclude))), key=str)
    with open(a.weights or oidn_ft_blob(SHIPPED_MODEL, a.network), "rb") as f:
        weights = f.read()
    blobs = {b: blob_at(a.network, weights, a.weights_blend, b) for b in a.blends}
    result = {}
    for spp in a.spp:
        result[spp] = {str(k): gains(store, k, spp, a.network, blobs) for k in keys}
        print(f"{spp} spp, {len(keys)} frames: mean over each frame's realizations of PSNR − stock OIDN "
              f"({a.network}), dB")
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
