"""Shared helpers of the evaluation tests: a small synthetic store written with the store API.

One test scene with ``FRAMES`` frames of ``W``×``H`` pixels: GT_clean is a noise-free smooth
pattern, GT1/GT2 (64 spp) and four 4-spp stacks are that pattern with multiplicative Gaussian
noise of standard deviation 0.7·sqrt(4/spp), so pooling k stacks behaves like k times the
samples. Per-image render seconds follow t(N) = A + B·N exactly.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from evaluate.stability import synthetic_buffers
from pipeline import schema
from pipeline.store import Store, image_names

H, W = 24, 32
FRAMES = 2
STACKS = 4
GT_SPP = 64
A, B = 0.01, 0.001          # render seconds = A + B * spp
SCENE = "s00001"


def make_store(root: Path) -> Path:
    store = Store(root)
    names = image_names(STACKS)
    store.write_manifest({"config": {}, "scenes": [SCENE], "splits": {"train": [], "val": [], "test": [SCENE]},
                          "images": names, "packages": {}})
    store.write_scene_manifest(SCENE, {"scene": SCENE, "index": 1, "split": "test", "frames": FRAMES,
                                       "resolution": [W, H], "gt_spp": GT_SPP, "stack_spp": 4, "stacks": STACKS,
                                       "images": names})
    for f in range(FRAMES):
        phase = 0.9 * f
        records = {}
        for k, name in enumerate(names):
            spp = GT_SPP if name.startswith("gt") else 4
            buf = synthetic_buffers(H, W, seed=100 * f + k, noise=0.7 * math.sqrt(4 / spp), spp=spp, phase=phase)
            records[name] = store.write_image(SCENE, f, name, buf, meta={
                "image": name, "scene": SCENE, "frame": f, "spp": spp, "render_seconds": A + B * spp})
        clean = synthetic_buffers(H, W, noise=0.0, phase=phase)["color"]
        store.write_image(SCENE, f, "gt_clean", {"color": clean, schema.variance_name("color"): np.zeros_like(clean)},
                          meta={"image": "gt_clean", "scene": SCENE, "frame": f, "source": "gt1"})
        store.write_frame_record(SCENE, f, {"scene": SCENE, "frame": f, "width": W, "height": H, "images": records})
    return root
