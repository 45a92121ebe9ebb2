"""Where on one hand-made scene the shipped model loses to OIDN: errors by brightness, a picture, and the
model with one buffer group withheld at a time (what a user's EXR without it would get).

    python docs/oidn_guards/scene_diag.py ext_val_sunlit_room 16 OUT_PREFIX [-- config overrides, e.g. runs=R]

Writes OUT_PREFIX.png (noisy | OIDN | the base alone | ours | GT1 | where ours is worse (red) or better
(green) than its base, squared error on x/(1+x)) and OUT_PREFIX_crop.png (rows and columns --crop y0,y1,x0,x1
of the same, and |ours − base| last); prints PSNRs, the squared error by brightness decile, and ours − OIDN
with each group withheld (mean over the first four realizations).
"""
import argparse
import sys

import numpy as np
from PIL import Image

from mcdenoise.evaluate.methods import Loader
from mcdenoise.evaluate.run import realization_stacks
from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.metrics import psnr, reinhard
from mcdenoise.pipeline.store import Store

GROUPS = {"variances": lambda k: "variance" in k,
          "radiance split": lambda k: k.split(".")[0] in {"emission", "diffuse_direct", "specular_direct",
                                                          "diffuse_indirect", "specular_indirect"},
          "material buffers": lambda k: k.split(".")[0] in {"roughness", "metallic", "transmission", "depth"}}


def show(x):
    return np.clip(reinhard(x), 0, 1) ** (1 / 2.2)


def save(panels, path, zoom):
    row = np.concatenate(panels, 1)
    img = Image.fromarray((row * 255).astype(np.uint8))
    img.resize((row.shape[1] * zoom, row.shape[0] * zoom), Image.NEAREST).save(path)


def main(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("spp", type=int)
    ap.add_argument("out")
    ap.add_argument("--store", default="data/external")
    ap.add_argument("--crop", default="80,110,25,75")
    ap.add_argument("overrides", nargs="*")
    a = ap.parse_args(argv)
    store, loader = Store(a.store), Loader(load_config("configs/default.yaml", a.overrides or ["runs=/tmp/norun"]))
    key = next(k for k in store.frames("external") if k.scene == a.scene)
    ref = store.read_image(key.scene, key.frame, "gt1", ["color"])[0]["color"]
    methods = {n: loader.load(n, a.spp) for n in ("oidn", "base_only", "ours")}
    withheld = {name: [] for name in ["none", *GROUPS]}
    for r, stacks in enumerate(realization_stacks(store, key, a.spp, n=1 << 30)):
        if r == 4:
            break
        buf = store.read(key.scene, key.frame, a.spp, stacks=stacks)
        for m in methods.values():
            m.set_frame(store, key)
        out = {n: np.asarray(m.denoise(buf), np.float32) for n, m in methods.items()}
        o = psnr(out["oidn"], ref)
        withheld["none"].append(psnr(out["ours"], ref) - o)
        for name, drop in GROUPS.items():
            kept = {k: v for k, v in buf.items() if not drop(k)}
            withheld[name].append(psnr(np.asarray(methods["ours"].denoise(kept), np.float32), ref) - o)
        if r == 0:
            first, noisy = out, buf["color"]
    print({n: round(psnr(v, ref), 3) for n, v in first.items()}, "(first realization)")
    lum = ref.mean(-1)
    edges = np.quantile(lum, np.linspace(0, 1, 11))
    for n, v in first.items():
        e = ((reinhard(v) - reinhard(ref)) ** 2).mean(-1)
        print(f"{n:10s} squared error x1e4 by brightness decile:",
              " ".join(f"{e[(lum >= edges[i]) & (lum <= edges[i + 1])].mean() * 1e4:.2f}" for i in range(10)))
    print("ours − OIDN with a group withheld:", {k: round(float(np.mean(v)), 3) for k, v in withheld.items()})
    diff = ((show(first["ours"]) - show(ref)) ** 2).mean(-1) - ((show(first["base_only"]) - show(ref)) ** 2).mean(-1)
    s = max(np.abs(diff).max() / 3, 1e-12)
    where = np.stack([np.clip(diff / s, 0, 1), np.clip(-diff / s, 0, 1), np.zeros_like(diff)], -1)
    save([show(noisy), show(first["oidn"]), show(first["base_only"]), show(first["ours"]), show(ref), where],
         f"{a.out}.png", 3)
    y0, y1, x0, x1 = (int(v) for v in a.crop.split(","))
    c = (slice(y0, y1), slice(x0, x1))
    moved = np.abs(first["ours"][c] - first["base_only"][c]).mean(-1)
    save([show(noisy[c]), show(first["oidn"][c]), show(first["base_only"][c]), show(first["ours"][c]), show(ref[c]),
          np.repeat((moved / max(moved.max(), 1e-12))[..., None], 3, -1)], f"{a.out}_crop.png", 6)


if __name__ == "__main__":
    main(sys.argv[1:])
