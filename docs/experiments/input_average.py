"""Averaging the noisy input over the previous frames before OIDN, against the temporal filter on OIDN's output
(docs/sequences.md, "Averaging the input over the previous frames" and "Read without resampling", has the rules
this measures for).

    python docs/experiments/input_average.py --store data/sequence --split val
    python docs/experiments/input_average.py --store data/val_seq --split external --kernel nearest --windows 2,4,8

Per sequence of the split and per spp (the first noise realization): frame t's input averaged with up to
window - 1 frames before it, each read straight into frame t (``motion.reproject_view`` between the two frames,
then ``--kernel``), over the frames valid at each pixel: all the radiance (``colour/W``) or only the diffuse
components (``diffuse/W``); OIDN's final-frame mode on it; each also with the temporal filter on its output
(``+filter``, or ``+filter:W`` for each of ``--weights``). The baseline ``filter`` is
``oidn_prefilter_temporal``. ``--specular R,...`` adds, for each radius R, the filter whose weight per pixel is ``w + (1 - w) * s`` with
``s`` the share of reflected light in the denoiser's input (``specular_share``), labelled +spec:R.
``--ahead A,...`` averages the A frames after frame t too (labelled ``/W>A``); ``--two-sided`` adds, for each
filtered candidate that reads frames after, the filter on both sides (``two_sided``, labelled +filter2; with
``--reach R`` also its backward filter started R frames after, +filter2:R).
``--ours CANDIDATE`` adds train/shipped's model on that candidate's input, beside ``ours`` and ``ours_filter``
(a candidate ending +filter2 with the causal filter beside it too). Prints per method and spp the mean over
sequences of (mean over t >= 1 of PSNR - oidn_prefilter's), the mean instability (as the sequence page measures
it, through GT1's motion) and the sequences below oidn_prefilter.
"""
from __future__ import annotations

import numpy as np
from history_clamp import arguments, oidn_sequences

from mcdenoise.evaluate.scoring import score
from mcdenoise.pipeline import motion, temporal
from mcdenoise.pipeline.schema import RADIANCE_COMPONENTS
from mcdenoise.pipeline.store import Store
from mcdenoise.train import oidn


def averaged(frames, t: int, window: int, kind: str, kernel: str, gate: float | None = None,
             ahead: int = 0) -> dict[str, np.ndarray]:
    """Frame t's buffers, its input averaged (``temporal.average_input``) over it, the frames t-window+1 .. t-1 and
    the ``ahead`` frames after it (those in the sequence)."""
    past = frames[max(0, t - window + 1):t][::-1] + frames[t + 1:t + 1 + ahead]
    traced = motion.trace(frames[t].views["input"], [f.views["input"] for f in past])
    return temporal.average_input(frames[t].buffers, [f.buffers for f in past], traced, kind, kernel, gate)[0]


LUMINANCE = np.array([0.2126, 0.7152, 0.0722], np.float64)


def specular_share(buffers: dict[str, np.ndarray], radius: int) -> np.ndarray:
    """(H, W) share of the specular components in the luminance of all radiance components, each box-filtered
    over a (2 radius + 1)^2 window first (edge pixels over the window's part inside the image); 0 where no light."""
    def box(image):
        lum = np.maximum(np.asarray(image, np.float64) @ LUMINANCE, 0.0)
        padded = np.pad(lum, radius)
        h, w = lum.shape
        return sum(padded[dy:dy + h, dx:dx + w] for dy in range(2 * radius + 1) for dx in range(2 * radius + 1))
    spec = box(buffers["specular_direct"] + buffers["specular_indirect"])
    total = box(sum(buffers[n] for n in RADIANCE_COMPONENTS))
    return np.clip(np.divide(spec, total, out=np.zeros_like(spec), where=total > 0), 0.0, 1.0)


def filtered(outputs, frames, weight, shares=None):
    """The temporal filter along ``outputs`` (its own previous output as the history); with ``shares`` (per frame,
    (H, W)) the new frame's weight per pixel is weight + (1 - weight) * share."""
    out = [outputs[0]]
    for t in range(1, len(frames)):
        history, valid = motion.warp_previous(out[t - 1], frames[t].views["input"], frames[t - 1].views["input"])
        if shares is None:
            out.append(temporal.blend_history(outputs[t], history, valid, weight))
            continue
        current = np.asarray(outputs[t], np.float32)
        lo, hi = temporal.neighbourhood_range(current)
        w = (weight + (1.0 - weight) * shares[t])[..., None].astype(np.float32)
        y = w * current + (1.0 - w) * np.clip(history, lo, hi)
        out.append(np.where(valid[..., None], y, current))
    return out


def two_sided(outputs, frames, weight, ahead, reach=None):
    """The filter on both sides (``temporal.filtered`` with ``ahead`` frames after, the backward filter from ``reach``
    of them; docs/sequences.md, "The filter on both sides")."""
    return [y for y, _ in temporal.filtered(zip(outputs, [f.views["input"] for f in frames]), weight, ahead, reach)]


def instabilities(outputs, frames) -> list[float]:
    """Per t >= 1, ``temporal.instability`` through GT1's motion (as ``evaluate.sequence.score_sequence``)."""
    res = []
    for t in range(1, len(frames)):
        xy, valid = motion.reproject_view(frames[t].views["gt1"], frames[t - 1].views["gt1"])
        res.append(temporal.instability(outputs[t], motion.warp(outputs[t - 1], xy, valid), frames[t].reference,
                                        motion.warp(frames[t - 1].reference, xy, valid), valid))
    return res


def means(gain: dict[int, dict[str, float]], unsteady: dict[int, dict[str, float]], spps: list[int]):
    """Per spp, of one method's {spp: {sequence: value}}: (the mean gain, the mean instability, the sequences with a
    gain below 0)."""
    return ([float(np.mean(list(gain[s].values()))) for s in spps],
            [float(np.mean(list(unsteady[s].values()))) for s in spps],
            [sum(v < 0 for v in gain[s].values()) for s in spps])


def main() -> int:
    ap = arguments(__doc__)
    ap.add_argument("--kernel", default="catmull_rom", choices=["nearest", "bilinear", "catmull_rom"],
                    help="how a past frame's input is read")
    ap.add_argument("--windows", default="8", help="frames averaged, frame t included (comma-separated)")
    ap.add_argument("--kinds", default="colour,diffuse",
                    help="what is averaged: colour, diffuse, irradiance, components (comma-separated)")
    ap.add_argument("--gates", default="none",
                    help="temporal.average_input's gate: none, or standard deviations (comma-separated)")
    ap.add_argument("--ahead", default="0", help="frames after frame t averaged too (comma-separated; the window "
                                                 "counts frame t and those before it)")
    ap.add_argument("--weights", help="the filter's weights on the averaged input (comma-separated; default "
                                     "--weight): each candidate with the filter once per weight, labelled +filter:W")
    ap.add_argument("--specular", default="", help="box radii of the reflected share's per-pixel filter weight "
                                                  "(comma-separated; each filtered candidate once more per radius)")
    ap.add_argument("--two-sided", action="store_true",
                    help="each filtered candidate that reads frames after also with the filter on both sides")
    ap.add_argument("--reach", type=int, help="--two-sided: also with the backward filter from this many frames after "
                                              "(labelled +filter2:R)")
    ap.add_argument("--ours", metavar="CANDIDATE",
                    help="also train/shipped's model on that candidate's input (e.g. colour/4+filter), against "
                         "ours and ours_filter")
    args = ap.parse_args()
    store = Store(args.store)
    spps = [int(s) for s in args.spp.split(",")]
    windows = [int(w) for w in args.windows.split(",")]
    gates = [None if g == "none" else float(g) for g in args.gates.split(",")]
    weights = [float(w) for w in args.weights.split(",")] if args.weights else [args.weight]
    aheads = [int(a) for a in args.ahead.split(",")]
    # a: frames ahead; f: the filter's weight, or None without the filter
    candidates = [(kind, w, g, a, f) for kind in args.kinds.split(",") for w in windows for g in gates
                  for a in aheads for f in (None, *weights)]
    label = lambda kind, w, g, a, f: (f"{kind}/{w}" + (f">{a}" if a else "") + (f"@{g:g}" if g else "")  # noqa: E731
                                      + ("" if f is None else "+filter" if not args.weights else f"+filter:{f:g}"))
    radii = [int(r) for r in args.specular.split(",") if r]
    spec_names = [f"{base}+spec:{r}" for base in ["filter", *(label(*c) for c in candidates if c[3] is not None)]
                  for r in radii]
    both = [label(*c) for c in candidates if c[4] is not None and c[3]] if args.two_sided else []
    names = ["oidn_prefilter", "filter", *(label(*c) for c in candidates), *(f"{n}2" for n in both),
             *(f"{n}2:{args.reach}" for n in both if args.reach is not None), *spec_names]
    if args.ours:
        from mcdenoise.train.infer import load_denoiser
        model = load_denoiser("train/shipped")
        ours_kind, rest = args.ours.split("/")
        ours_both = rest.endswith("+filter2")
        rest = rest.removesuffix("2") if ours_both else rest
        ours_filter, rest = rest.endswith("+filter"), rest.removesuffix("+filter")
        ours_window, _, gate_text = rest.partition("@")
        ours_window, _, ahead_text = ours_window.partition(">")
        ours_window, ours_gate = int(ours_window), float(gate_text) if gate_text else None
        names += ["ours", "ours_filter", *([f"ours {args.ours[:-1]}"] if ours_both else []), f"ours {args.ours}"]
    gain: dict[str, dict[int, dict[str, float]]] = {n: {s: {} for s in spps} for n in names}
    unsteady: dict[str, dict[int, dict[str, float]]] = {n: {s: {} for s in spps} for n in names}
    first: dict[str, dict[int, dict[str, float]]] = {n: {s: {} for s in spps} for n in names}   # t = 0
    for spp in spps:
        for name, frames, base in oidn_sequences(store, args.split, spp):
            runs = {"oidn_prefilter": base, "filter": filtered(base, frames, args.weight)}
            for r in radii:
                runs[f"filter+spec:{r}"] = filtered(base, frames, args.weight,
                                                    [specular_share(f.buffers, r) for f in frames])
            inputs = {}
            for kind, w, g, a, weight in candidates:
                if weight is not None:
                    unfiltered = runs[label(kind, w, g, a, None)]
                    runs[label(kind, w, g, a, weight)] = filtered(unfiltered, frames, weight)
                    if label(kind, w, g, a, weight) in both:
                        runs[label(kind, w, g, a, weight) + "2"] = two_sided(unfiltered, frames, weight, a)
                        if args.reach is not None:
                            runs[label(kind, w, g, a, weight) + f"2:{args.reach}"] = two_sided(
                                unfiltered, frames, weight, a, args.reach)
                    for r in radii:
                        runs[f"{label(kind, w, g, a, weight)}+spec:{r}"] = filtered(
                            unfiltered, frames, weight, [specular_share(b, r) for b in inputs[kind, w, g, a]])
                    continue
                inputs[kind, w, g, a] = [averaged(frames, t, w, kind, args.kernel, g, a) for t in range(len(frames))]
                runs[label(kind, w, g, a, None)] = [
                    oidn.denoise({k: b[k] for k in ("color", "albedo", "normal")}, aux=True, clean_aux=True)
                    for b in inputs[kind, w, g, a]]
            if args.ours:
                ours = [model.denoise(f.buffers, spp) for f in frames]
                runs["ours"], runs["ours_filter"] = ours, filtered(ours, frames, args.weight)
                avg = [model.denoise(averaged(frames, t, ours_window, ours_kind, args.kernel, ours_gate,
                                                int(ahead_text or 0)), spp)
                       for t in range(len(frames))]
                if ours_both:           # the causal filter on the same outputs, beside
                    runs[f"ours {args.ours[:-1]}"] = filtered(avg, frames, args.weight)
                runs[f"ours {args.ours}"] = (two_sided(avg, frames, args.weight, int(ahead_text or 0)) if ours_both
                                             else filtered(avg, frames, args.weight) if ours_filter else avg)
            psnr = {n: [score(y, f.reference, ["psnr"])["psnr"] for y, f in zip(out, frames)]
                    for n, out in runs.items()}
            for n, out in runs.items():
                gain[n][spp][name] = float(np.mean(np.subtract(psnr[n][1:], psnr["oidn_prefilter"][1:])))
                first[n][spp][name] = psnr[n][0] - psnr["oidn_prefilter"][0]
                unsteady[n][spp][name] = float(np.nanmean(instabilities(out, frames)))
            print(f"{spp} spp {name}: " + ", ".join(f"{n} {gain[n][spp][name]:+.3f}" for n in names[1:]), flush=True)
    print(f"\n{args.store} {args.split}: {len(gain['filter'][spps[0]])} sequences, {args.kernel} read, filter "
          f"weight {args.weight:g}, t >= 1, PSNR gain over oidn_prefilter and instability (means over sequences)")
    print("| method | " + " | ".join(f"gain {s} spp" for s in spps) + " | mean gain | "
          + " | ".join(f"instability {s} spp" for s in spps) + " | mean | sequences below, "
          + " / ".join(map(str, spps)) + " spp | t = 0: gain " + " / ".join(map(str, spps)) + " spp |")
    print("| --- |" + " ---: |" * (2 * len(spps) + 2) + " --- | ---: |")
    for n in names:
        per, inst, below = means(gain[n], unsteady[n], spps)
        print(f"| {n} | " + " | ".join(f"{v:+.3f}" for v in per) + f" | {np.mean(per):+.3f} | "
              + " | ".join(f"{v:.4f}" for v in inst) + f" | {np.mean(inst):.4f} | " + " / ".join(map(str, below)) + " | "
              + " / ".join(f"{np.mean(list(first[n][s].values())):+.3f}" for s in spps) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
