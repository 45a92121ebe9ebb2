"""Does the shipped model know its training noise? ``ours`` − OIDN at 4 spp on every realization of some
frames of a ``data/ship`` split: the train pack holds each frame's first two 4-spp stacks (``train.pack.
PACK_VARIANTS``), so on train frames realizations 0-1 were seen and 2-15 were not.

    python docs/oidn_guards/noise_overfit.py train 30 OUT.json [-- config overrides]
"""
import json
import sys

import numpy as np

from mcdenoise.evaluate.methods import Loader
from mcdenoise.pipeline.config import load_config
from mcdenoise.pipeline.store import Store

sys.path.insert(0, "docs/oidn_guards")
from realizations import realization_psnrs  # noqa: E402


def main(split: str, count: int, out: str, overrides: list[str]) -> None:
    cfg = load_config("configs/default.yaml", overrides or ["runs=/tmp/norun"])
    store = Store("data/ship")
    keys = sorted(store.frames(split), key=str)
    keys = keys[:: max(1, len(keys) // count)][:count]
    loader = Loader(cfg)
    methods = {n: loader.load(n, 4) for n in ("oidn", "ours")}
    gains = {}
    for key in keys:
        r = realization_psnrs(methods, store, key, 4)
        gains[str(key)] = np.subtract(r["ours"], r["oidn"]).tolist()
    with open(out, "w") as f:
        json.dump(gains, f)
    d = np.array(list(gains.values()))
    print(f"{split}: {len(d)} frames; ours − oidn at 4 spp, realizations 0-1 {d[:, :2].mean():+.4f}, "
          f"2-15 {d[:, 2:].mean():+.4f}")


if __name__ == "__main__":
    a = sys.argv[1:]
    main(a[0], int(a[1]), a[2], a[4:] if len(a) > 3 and a[3] == "--" else a[3:])
