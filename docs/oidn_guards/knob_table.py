"""The shipped model's two inference-time knobs (ship_knobs.py) on both validation sets, every noise
realization: `ours` and `base_only` − OIDN, PSNR dB (python docs/oidn_guards/knob_table.py).

Files: realizations/knobs/b<blend×100>c<control×100>_{ext,dv}.json, written by realizations.py on the
nine hand-made val_* scenes (data/external, GT1 at 4096 spp) and on the default config's 8 val frames
(--store data/default --split val --prefix "", against GT_clean)."""
import json
from pathlib import Path

import numpy as np

KNOBS = Path(__file__).parent / "realizations" / "knobs"


def gains(result, method, spp):
    """{scene or frame: mean gain over its realizations}."""
    return {k: float(np.mean(np.subtract(v[method], v["oidn"]))) for k, v in result[spp].items()}


def row(name, method):
    ext = json.loads((KNOBS / f"{name}_ext.json").read_text())
    dv_path = KNOBS / f"{name}_dv.json"
    e4, e16 = gains(ext, method, "4"), gains(ext, method, "16")
    worst = min(e4, key=e4.get)
    cells = [f"{np.mean(list(e4.values())):+.3f}", f"{e4[worst]:+.3f} {worst.removeprefix('ext_val_')}",
             f"{np.mean(list(e16.values())):+.3f}"]
    if dv_path.exists():
        dv = json.loads(dv_path.read_text())
        cells.append(" / ".join(f"{np.mean(list(gains(dv, method, s).values())):+.3f}" for s in ("4", "16", "64")))
    else:
        cells.append("")
    b, c = name[1:].split("c")
    return f"| {int(b) / 100:g} | {int(c) / 100:g} | {method} | " + " | ".join(cells) + " |"


if __name__ == "__main__":
    print("| base blend | control scale | method | nine val_* scenes, 4 spp | worst scene, 4 spp | nine, 16 spp "
          "| default val 4 / 16 / 64 spp |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    names = sorted({p.name.split("_")[0] for p in KNOBS.glob("b*_ext.json")},
                   key=lambda n: (int(n[1:].split("c")[0]), int(n.split("c")[1])))
    for name in names:
        for method in ("ours", "base_only"):
            if method == "base_only" and not name.endswith("c100"):
                continue                          # the base alone does not depend on the control scale
            print(row(name, method))
