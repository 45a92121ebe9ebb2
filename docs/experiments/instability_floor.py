"""How steady can an output be measured to be? (docs/sequences.md, "What the instability can measure")

    python docs/experiments/instability_floor.py --store data/sequence --split val
    python docs/experiments/instability_floor.py --store data/val_seq --split external

The temporal instability (``temporal.instability``) compares an output's frame-to-frame change with the
reference's; a reference rendered with finitely many samples changes from frame to frame by its own noise too,
so even the true image scores above zero. Per sequence of the split and frame t >= 1, warped as the sequence
page warps (``evaluate.sequence.score_sequence``: both frames' GT1 depth and normal), this scores:

- ``oidn_prefilter`` at each spp (first noise realization): the denominator of the goal's ratio;
- ``gt1``, ``gt2``: the two independent high-sample renders of the frame (``dataset.gt_spp`` each), as if they were
  a method's output (the one that is the reference itself scores 0 and is left out).

Against GT1 as reference (an external scene), GT2 differs from it by two independent renders' noise, so the
true image would score about GT2's score / sqrt(2) (exactly so for Gaussian noise of equal spread): the floor
under which no method can be measured. Against gt_clean (the cleaner's output of GT1 and GT2) the floor is not
observable; GT1's and GT2's scores say how steady an image with ``gt_spp`` samples is measured to be.
Prints the mean over sequences of each one's mean over t >= 1, and each as a fraction of oidn_prefilter's.
"""
from __future__ import annotations

import math

import numpy as np
from history_clamp import arguments, oidn_sequences  # beside this file: python puts its folder on the path

from mcdenoise.evaluate.run import _reference_name
from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.store import Store


def sequence_instability(images: list[np.ndarray], frames) -> float:
    """Mean over t >= 1 of ``temporal.instability`` of ``images`` against the frames' references, warped with
    their GT1 views (as the sequence page scores); NaN frames (nothing valid) left out."""
    scores = []
    for t in range(1, len(frames)):
        xy, valid = motion.reproject_view(frames[t].views["gt1"], frames[t - 1].views["gt1"])
        scores.append(temporal.instability(images[t], motion.warp(images[t - 1], xy, valid), frames[t].reference,
                                           motion.warp(frames[t - 1].reference, xy, valid), valid))
    return float(np.nanmean(scores))


def main() -> int:
    args = arguments(__doc__).parse_args()
    store = Store(args.store)
    spps = [int(s) for s in args.spp.split(",")]
    rows: dict[str, list[float]] = {}
    reference_names = set()
    for spp in spps:
        per_seq = []
        for _, frames, base in oidn_sequences(store, args.split, spp):
            per_seq.append(sequence_instability(base, frames))
            if spp == spps[0]:       # the renders do not depend on spp: scored once
                ref = _reference_name(store, frames[0].key, args.split == "external")
                reference_names.add(ref)
                for name in ("gt1", "gt2"):
                    if name != ref:
                        images = [store.read_image(f.key.scene, f.key.frame, name, ["color"])[0]["color"]
                                  for f in frames]
                        rows.setdefault(name, []).append(sequence_instability(images, frames))
        rows[f"oidn_prefilter, {spp} spp"] = per_seq
        print(f"{spp} spp: oidn_prefilter {np.mean(per_seq):.4f} over {len(per_seq)} sequences", flush=True)
    print(f"\n{args.store} {args.split}: reference {', '.join(sorted(reference_names))}; instability, t >= 1, "
          "mean over sequences; ÷: as a fraction of oidn_prefilter's at that spp")
    print("| image | instability | " + " | ".join(f"÷ at {s} spp" for s in spps) + " |")
    print("| --- | ---: |" + " ---: |" * len(spps))
    denominators = [float(np.mean(rows[f"oidn_prefilter, {s} spp"])) for s in spps]
    table = {k: float(np.mean(v)) for k, v in rows.items()}
    if reference_names == {"gt1"} and "gt2" in table:
        table["true image (GT2's ÷ √2)"] = table["gt2"] / math.sqrt(2)
    for name, value in table.items():
        print(f"| {name} | {value:.4f} | " + " | ".join(f"{value / d:.2f}" for d in denominators) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
