"""The temporal filter's history read and blended on tonemapped values, against radiance as it ships
(docs/sequences.md, "The history's read around small bright lights", has the rule this measures for).

    python docs/experiments/history_read.py --store data/sequence --split val
    python docs/experiments/history_read.py --store data/val_seq --split external

Per sequence of the split and per spp (the first noise realization): ``oidn_prefilter_temporal`` as
``make eval`` runs it (the diffuse light averaged over 8 frames and 7 after, gated at 2, OIDN's final-frame mode
on it, the filter on both sides at weight 0.7), with the history

- ``radiance``: read with Catmull-Rom on the radiance and blended on it (the read before the rule chose ``read``);
- ``read``: read with Catmull-Rom on T(x) = x / (1 + x) per channel, brought back with T^-1(u) = u / (1 - u),
  blended on the radiance (``motion.warp_previous``, what ships);
- ``read+blend``: read as ``read``, then clamped and blended on T, brought back with T^-1.

Prints per candidate and spp the mean over sequences of (mean over t >= 1 of PSNR - oidn_prefilter's), the mean
instability (``input_average.instabilities``) and the sequences below oidn_prefilter, then which move gains and
loses most; beside, not chosen on: HDR-FLIP (mean over t >= 1 and sequences) and how bright the lights come out
(the output's luminance over the reference's, summed over the pixels whose reference luminance is above 4).
"""
from __future__ import annotations

import contextlib

import numpy as np
from history_clamp import arguments, oidn_sequences
from input_average import averaged, instabilities, means, two_sided

from mcdenoise.evaluate.scoring import score
from mcdenoise.pipeline import metrics, motion, temporal
from mcdenoise.pipeline.store import Store
from mcdenoise.train import oidn


def warp_previous_radiance(image_prev, view, view_prev, traced=None):
    """The history read before: Catmull-Rom on the radiance itself (0 where invalid)."""
    xy, valid = motion.reproject_view(view, view_prev) if traced is None else traced
    return motion.warp(np.asarray(image_prev, np.float32), xy, valid, kernel="catmull_rom"), valid


def tonemap(x):
    return metrics.reinhard(np.asarray(x, np.float64))


BLEND_SIDES = temporal.blend_sides


def blend_sides_tonemapped(current, sides, weight, clamp=True, box=None):
    """``temporal.blend_sides`` on T of every image (the clamp's box included), brought back with T^-1."""
    box = None if box is None else (tonemap(box[0]), tonemap(box[1]))
    out = BLEND_SIDES(tonemap(current).astype(np.float32), [(tonemap(h).astype(np.float32), v) for h, v in sides],
                      weight, clamp, None if box is None else tuple(b.astype(np.float32) for b in box))
    return metrics.inverse_reinhard(out).astype(np.float32)


@contextlib.contextmanager
def history(candidate: str):
    """The filter's history read (and blended) as ``candidate`` says, inside the block."""
    saved = motion.warp_previous, temporal.blend_sides
    if candidate == "radiance":
        motion.warp_previous = warp_previous_radiance
    if candidate == "read+blend":
        temporal.blend_sides = blend_sides_tonemapped
    try:
        yield
    finally:
        motion.warp_previous, temporal.blend_sides = saved


CANDIDATES = ("radiance", "read", "read+blend")
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def main() -> int:
    ap = arguments(__doc__)
    ap.add_argument("--ahead", type=int, default=7)
    args = ap.parse_args()
    store = Store(args.store)
    spps = [int(s) for s in args.spp.split(",")]
    gain = {c: {s: {} for s in spps} for c in CANDIDATES}
    unsteady = {c: {s: {} for s in spps} for c in CANDIDATES}
    flip = {c: {s: {} for s in spps} for c in CANDIDATES}
    lights = {c: {s: [0.0, 0.0] for s in spps} for c in CANDIDATES}    # output, reference luminance on the lights
    for spp in spps:
        for name, frames, base in oidn_sequences(store, args.split, spp):
            inputs = [averaged(frames, t, 8, "diffuse", "nearest", 2.0, args.ahead) for t in range(len(frames))]
            outputs = [oidn.denoise({k: b[k] for k in ("color", "albedo", "normal")}, aux=True, clean_aux=True)
                       for b in inputs]
            ref = [score(y, f.reference, ["psnr"])["psnr"] for y, f in zip(base, frames)]
            for c in CANDIDATES:
                with history(c):
                    out = two_sided(outputs, frames, args.weight, args.ahead, temporal.BACK_REACH)
                psnr = [score(y, f.reference, ["psnr"])["psnr"] for y, f in zip(out, frames)]
                gain[c][spp][name] = float(np.mean(np.subtract(psnr[1:], ref[1:])))
                unsteady[c][spp][name] = float(np.nanmean(instabilities(out, frames)))
                flip[c][spp][name] = float(np.mean([score(y, f.reference, ["hdr_flip"])["hdr_flip"]
                                                    for y, f in zip(out[1:], frames[1:])]))
                for y, f in zip(out[1:], frames[1:]):
                    bright = f.reference @ LUMINANCE > 4.0
                    lights[c][spp][0] += float((y[bright] @ LUMINANCE).sum())
                    lights[c][spp][1] += float((f.reference[bright] @ LUMINANCE).sum())
            print(f"{spp} spp {name}: " + ", ".join(f"{c} {gain[c][spp][name]:+.3f}" for c in CANDIDATES), flush=True)
    print(f"\n{args.store} {args.split}: {len(gain['radiance'][spps[0]])} sequences, filter weight {args.weight:g} on "
          f"both sides, t >= 1, PSNR gain over oidn_prefilter and instability (means over sequences)")
    print("| history | " + " | ".join(f"gain {s} spp" for s in spps) + " | mean gain | "
          + " | ".join(f"instability {s} spp" for s in spps) + " | mean | sequences below, "
          + " / ".join(map(str, spps)) + " spp |")
    print("| --- |" + " ---: |" * (2 * len(spps) + 2) + " --- |")
    for c in CANDIDATES:
        per, inst, below = means(gain[c], unsteady[c], spps)
        print(f"| {c} | " + " | ".join(f"{v:+.3f}" for v in per) + f" | {np.mean(per):+.3f} | "
              + " | ".join(f"{v:.4f}" for v in inst) + f" | {np.mean(inst):.4f} | " + " / ".join(map(str, below)) + " |")
    print("beside, not chosen on: " + "; ".join(
        f"{c}: HDR-FLIP " + " / ".join(f"{np.mean(list(flip[c][s].values())):.4f}" for s in spps) + ", lights "
        + " / ".join(f"{lights[c][s][0] / lights[c][s][1]:.3f}" if lights[c][s][1] else "none" for s in spps)
        for c in CANDIDATES) + f" ({' / '.join(map(str, spps))} spp)")
    for c in CANDIDATES[1:]:
        diff = {(n, s): gain[c][s][n] - gain["radiance"][s][n] for s in spps for n in gain[c][s]}
        order = sorted(diff, key=diff.get)
        print(f"{c} - radiance per sequence: lowest " + ", ".join(f"{n} {s} spp {diff[n, s]:+.3f}" for n, s in order[:3])
              + "; highest " + ", ".join(f"{n} {s} spp {diff[n, s]:+.3f}" for n, s in order[-3:]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
