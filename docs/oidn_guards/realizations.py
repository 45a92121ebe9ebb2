"""Methods − OIDN (or ``--reference``) on every noise realization the store holds, not only the first.

``make eval`` reads each frame at 4 spp from its first stack; a store frame has 16 stacks of 4 spp,
so 16 independent 4-spp inputs (and 4 at 16 spp). One realization's per-scene gain carries that
realization's noise (single scenes move by up to ±0.3 dB between realizations); the mean over all
of them says what the method does on the scene. Methods are loaded and run exactly as ``make eval``
runs them (``evaluate.methods.Loader``); PSNR is eval's (Reinhard tonemap, against GT1).

    python docs/oidn_guards/realizations.py --methods oidn_ft ours [--reference oidn] [--store data/external]
        [--split external] [--prefix ext_val] [--exclude P] [--spp 4 16] [--layers color albedo normal]
        -- [config overrides, e.g. runs=R oidn_ft.blend=0.5]
"""
import argparse
import json
import sys

import numpy as np

from mcdenoise.evaluate.methods import Loader
from mcdenoise.evaluate.run import realization_stacks
from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.metrics import psnr
from mcdenoise.pipeline.store import Store


def realization_psnrs(methods, store, key, spp, layers=()):
    """{method: [PSNR on each disjoint group of stacks that makes ``spp``]} for the frame ``key``,
    against the reference eval reads (GT_clean where the frame has one, else GT1); ``layers``: only these
    buffers reach the methods (an EXR from another renderer: ``color albedo normal``), else all."""
    ref_name = "gt_clean" if store.image_path(key.scene, key.frame, "gt_clean").exists() else "gt1"
    ref = store.read_image(key.scene, key.frame, ref_name, ["color"])[0]["color"]
    out = {name: [] for name in methods}
    for stacks in realization_stacks(store, key, spp, n=1 << 30):
        buffers = store.read(key.scene, key.frame, spp, stacks=stacks)
        buffers = {k: v for k, v in buffers.items() if k in layers} if layers else buffers
        for name, method in methods.items():
            method.set_frame(store, key)
            out[name].append(psnr(np.asarray(method.denoise(buffers), np.float32), ref))
    return out


def main(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("--methods", nargs="+", required=True)
    ap.add_argument("--store", default="data/external")
    ap.add_argument("--split", default="external", help="the store split whose frames are scored")
    ap.add_argument("--prefix", default="ext_val", help="score the split's scenes whose id starts with this")
    ap.add_argument("--exclude", default="", help="... and does not start with this")
    ap.add_argument("--spp", nargs="+", type=int, default=[4, 16])
    ap.add_argument("--config", default="configs/default.yaml")
    ap.add_argument("--json", default="")
    ap.add_argument("--layers", nargs="+", default=[], help="only these buffers reach the methods (default: all)")
    ap.add_argument("--reference", default="oidn", help="the method the others are compared with")
    ap.add_argument("overrides", nargs="*")
    a = ap.parse_args(argv)
    cfg = load_config(a.config, a.overrides)
    store = Store(a.store)
    keys = sorted((key for key in store.frames(a.split) if key.scene.startswith(a.prefix)
                   and not (a.exclude and key.scene.startswith(a.exclude))), key=str)
    label = (lambda key: key.scene) if a.split == "external" else str   # external scenes: one frame each
    loader, result = Loader(cfg), {}
    for spp in a.spp:
        methods = {name: loader.load(name, spp) for name in dict.fromkeys([a.reference, *a.methods])}
        result[spp] = {label(key): realization_psnrs(methods, store, key, spp, a.layers) for key in keys}
    for name in (m for m in a.methods if m != a.reference):
        print(f"{name} − {a.reference}, dB, the mean over realizations ± its standard error (first realization; range):")
        for spp in a.spp:
            means = {}
            for sid, r in result[spp].items():
                d = np.subtract(r[name], r[a.reference])
                means[sid] = d.mean()
                se = d.std(ddof=1) / len(d) ** 0.5 if len(d) > 1 else float("nan")
                print(f"  {spp:3d} spp {sid:28s} {d.mean():+.3f} ± {se:.3f} ({d[0]:+.2f}; {d.min():+.2f} … "
                      f"{d.max():+.2f}; {len(d)} realizations)")
            worst = min(means, key=means.get)
            print(f"  {spp:3d} spp mean over {len(means)} scenes {np.mean(list(means.values())):+.3f}, "
                  f"worst {means[worst]:+.3f} ({worst})")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({str(s): v for s, v in result.items()}, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
