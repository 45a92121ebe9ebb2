"""Averaging the noisy input over the previous frames before OIDN, against the temporal filter on OIDN's output
(docs/sequences.md, "Averaging the input over the previous frames", has the rule this measures for).

    python docs/experiments/input_average.py --store data/sequence --split val
    python docs/experiments/input_average.py --store data/val_seq --split external

Per sequence of the split and per spp (the first noise realization): frame t's input averaged with up to
``--window - 1`` frames before it, each warped straight into frame t (``motion.reproject_view`` between the two
frames, one Catmull-Rom read), over the frames valid at each pixel: the colour (``colour``) or only the diffuse
components, the rest of frame t (``diffuse``); OIDN's final-frame mode on it; each also with the temporal
filter on its output (``+filter``). The baseline ``filter`` is ``oidn_prefilter_temporal``. Prints per method
and spp the mean over sequences of (mean over t >= 1 of PSNR - oidn_prefilter's), the mean instability (as the
sequence page measures it, through GT1's motion) and the sequences below oidn_prefilter.
"""
from __future__ import annotations

import numpy as np
from history_clamp import arguments, oidn_sequences

from mcdenoise.evaluate.scoring import score
from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.store import Store
from mcdenoise.train import oidn

DIFFUSE = ("diffuse_direct", "diffuse_indirect")
REST = ("emission", "specular_direct", "specular_indirect")


def averaged(frames, t: int, window: int) -> tuple[np.ndarray, np.ndarray]:
    """(colour, diffuse) of frame t, each the mean over frame t and the frames t-window+1 .. t-1 valid at the
    pixel, every one warped straight into frame t."""
    own = frames[t].buffers
    total = np.concatenate([own["color"], own[DIFFUSE[0]] + own[DIFFUSE[1]]], axis=2).astype(np.float64)
    count = np.ones(total.shape[:2])
    for k in range(max(0, t - window + 1), t):
        b = frames[k].buffers
        xy, valid = motion.reproject_view(frames[t].views["input"], frames[k].views["input"])
        past = np.concatenate([b["color"], b[DIFFUSE[0]] + b[DIFFUSE[1]]], axis=2).astype(np.float32)
        total += motion.warp(past, xy, valid, kernel="catmull_rom")
        count += valid
    mean = (total / count[..., None]).astype(np.float32)
    return mean[..., :3], mean[..., 3:]


def filtered(outputs, frames, weight):
    """The temporal filter along ``outputs`` (its own previous output as the history)."""
    out = [outputs[0]]
    for t in range(1, len(frames)):
        history = motion.warp_previous(out[t - 1], frames[t].views["input"], frames[t - 1].views["input"])
        out.append(temporal.blend_history(outputs[t], *history, weight))
    return out


def instabilities(outputs, frames) -> list[float]:
    """Per t >= 1, ``temporal.instability`` through GT1's motion (as ``evaluate.sequence.score_sequence``)."""
    res = []
    for t in range(1, len(frames)):
        xy, valid = motion.reproject_view(frames[t].views["gt1"], frames[t - 1].views["gt1"])
        res.append(temporal.instability(outputs[t], motion.warp(outputs[t - 1], xy, valid), frames[t].reference,
                                        motion.warp(frames[t - 1].reference, xy, valid), valid))
    return res


def main() -> int:
    ap = arguments(__doc__)
    ap.add_argument("--window", type=int, default=8, help="frames averaged, frame t included")
    args = ap.parse_args()
    store = Store(args.store)
    spps = [int(s) for s in args.spp.split(",")]
    names = ["oidn_prefilter", "filter", "colour", "colour+filter", "diffuse", "diffuse+filter"]
    gain: dict[str, dict[int, dict[str, float]]] = {n: {s: {} for s in spps} for n in names}
    unsteady: dict[str, dict[int, dict[str, float]]] = {n: {s: {} for s in spps} for n in names}
    for spp in spps:
        for name, frames, base in oidn_sequences(store, args.split, spp):
            colour, diffuse = [], []
            for t, f in enumerate(frames):
                c, d = averaged(frames, t, args.window)
                aux = {"albedo": f.buffers["albedo"], "normal": f.buffers["normal"]}
                colour.append(oidn.denoise({"color": c, **aux}, aux=True, clean_aux=True))
                rest = sum(f.buffers[k] for k in REST)
                diffuse.append(oidn.denoise({"color": rest + d, **aux}, aux=True, clean_aux=True))
            runs = {"oidn_prefilter": base, "filter": filtered(base, frames, args.weight), "colour": colour,
                    "colour+filter": filtered(colour, frames, args.weight), "diffuse": diffuse,
                    "diffuse+filter": filtered(diffuse, frames, args.weight)}
            psnr = {n: [score(y, f.reference, ["psnr"])["psnr"] for y, f in zip(out, frames)]
                    for n, out in runs.items()}
            for n, out in runs.items():
                gain[n][spp][name] = float(np.mean(np.subtract(psnr[n][1:], psnr["oidn_prefilter"][1:])))
                unsteady[n][spp][name] = float(np.nanmean(instabilities(out, frames)))
            print(f"{spp} spp {name}: " + ", ".join(f"{n} {gain[n][spp][name]:+.3f}" for n in names[1:]), flush=True)
    print(f"\n{args.store} {args.split}: {len(next(iter(gain['filter'].values())))} sequences, window "
          f"{args.window}, filter weight {args.weight:g}, t >= 1, PSNR gain over oidn_prefilter and instability "
          "(means over sequences)")
    print("| method | " + " | ".join(f"gain {s} spp" for s in spps) + " | mean gain | "
          + " | ".join(f"instability {s} spp" for s in spps) + " | sequences below, " + " / ".join(map(str, spps))
          + " spp |")
    print("| --- |" + " ---: |" * (2 * len(spps) + 1) + " --- |")
    for n in names:
        per = [float(np.mean(list(gain[n][s].values()))) for s in spps]
        inst = [float(np.mean(list(unsteady[n][s].values()))) for s in spps]
        below = [sum(v < 0 for v in gain[n][s].values()) for s in spps]
        print(f"| {n} | " + " | ".join(f"{v:+.3f}" for v in per) + f" | {np.mean(per):+.3f} | "
              + " | ".join(f"{v:.4f}" for v in inst) + " | " + " / ".join(map(str, below)) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
