"""How good is each history a model reading the past could be given? (docs/sequences.md, "History sources")

    python docs/experiments/history_sources.py --store data/sequence --split val
    python docs/experiments/history_sources.py --store data/val_seq --split external

Per sequence of the split, spp and frame t >= 1 (first noise realization), each candidate previous image warped
into frame t as ``denoise --sequence`` warps it (the noisy input's depth and normal), scored against frame t's
reference on the pixels the warp finds valid:

- ``noisy``: the noisy colour of frame t-1;
- ``oidn``: OIDN's final-frame output of frame t-1 (what ``train.history`` gives in training);
- ``filtered``: the temporal filter's output of frame t-1 (``oidn_prefilter_temporal`` at the weight, itself
  built from frames 0..t-1: what a model fed its own accumulated output sees at inference, up to the model);

beside ``oidn(t)``: OIDN's output of frame t itself on the same pixels. Prints the mean over sequences of the
mean over t >= 1 of each PSNR, per spp.
"""
from __future__ import annotations

import numpy as np
from history_clamp import arguments, oidn_sequences  # beside this file: python puts its folder on the path

from mcdenoise.evaluate.sequence import sequences
from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.metrics import psnr
from mcdenoise.pipeline.store import Store

SOURCES = ("noisy", "oidn", "filtered", "oidn(t)")


def main() -> int:
    args = arguments(__doc__).parse_args()
    store = Store(args.store)
    seqs = sequences(store.frames(args.split))
    spps = [int(s) for s in args.spp.split(",")]
    table = {}
    for spp in spps:
        per_seq = {s: [] for s in SOURCES}
        coverage = []
        for _, frames, base in oidn_sequences(store, args.split, spp):
            filtered = [base[0]]
            scores = {s: [] for s in SOURCES}
            for t in range(1, len(frames)):
                view, view_prev = frames[t].views["input"], frames[t - 1].views["input"]
                xy, valid = motion.reproject_view(view, view_prev)
                coverage.append(float(valid.mean()))
                candidates = {"noisy": frames[t - 1].buffers["color"], "oidn": base[t - 1], "filtered": filtered[t - 1]}
                for source, image in candidates.items():
                    scores[source].append(psnr(motion.warp(image, xy, valid)[valid], frames[t].reference[valid]))
                scores["oidn(t)"].append(psnr(base[t][valid], frames[t].reference[valid]))
                filtered.append(temporal.blend_history(base[t], motion.warp(filtered[t - 1], xy, valid), valid,
                                                       args.weight))
            for source in SOURCES:
                per_seq[source].append(float(np.mean(scores[source])))
        table[spp] = ({s: float(np.mean(v)) for s, v in per_seq.items()}, float(np.mean(coverage)))
        print(f"{spp} spp: " + ", ".join(f"{s} {table[spp][0][s]:.2f}" for s in SOURCES)
              + f" (valid {100 * table[spp][1]:.0f} %)", flush=True)
    print(f"\n{args.store} {args.split}: {len(seqs)} sequences, t >= 1, PSNR on the warp's valid pixels "
          "(mean over sequences)")
    print("| previous image, warped | " + " | ".join(f"{s} spp" for s in spps) + " |")
    print("| --- |" + " ---: |" * len(spps))
    for source in SOURCES:
        print(f"| {source} | " + " | ".join(f"{table[s][0][source]:.2f}" for s in spps) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
