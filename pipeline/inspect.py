"""``python -m pipeline inspect STORE``: what a store holds, read from its manifests and headers.

Reads only manifests and EXR headers (no pixels), so it is fast on large stores.
"""
from __future__ import annotations

from collections import Counter

import numpy as np

from . import schema
from .exr import StoreError, encoding_of
from .metrics import PSNR_CEILING
from .store import Store


def inspect_store(root: str, frame: str | None = None) -> dict:
    store = Store(root)
    m = store.manifest()
    report: dict = {"store": str(root), "splits": {k: len(v) for k, v in m["splits"].items()},
                    "scenes": len(m["scenes"]), "packages": m.get("packages", {})}
    frames_total = frames_done = 0
    images = bytes_ = nonfinite = 0
    render_s: Counter = Counter()
    omitted: Counter = Counter()
    spp: Counter = Counter()
    encodings: Counter = Counter()
    incomplete = []
    gt_rows: list[tuple] = []
    for scene in m["scenes"]:
        sm = store.scene_manifest(scene)
        for f in range(int(sm["frames"])):
            frames_total += 1
            rec = store.frame_record(scene, f)
            if rec is None or not store.is_frame_complete(scene, f, sm["images"]):
                incomplete.append(f"{scene}/{f:03d}")
                continue
            frames_done += 1
            if "gt" in rec:
                gt_rows.append((sm.get("preset") or sm.get("split"), rec["gt"]))
            for name, img in rec["images"].items():
                images += 1
                bytes_ += img.get("bytes", 0)
                spp[img["spp"]] += 1
                render_s["gt" if name.startswith("gt") else "stack"] += img.get("render_seconds") or 0.0
                nonfinite += sum(img.get("nonfinite", {}).values())
                for ch in img.get("constants", {}):
                    omitted[ch] += 1
                encoding = encoding_of(img)
                encodings[(encoding["name"], encoding["beauty"])] += 1
    report.update({
        "frames": frames_total, "frames_complete": frames_done, "incomplete": incomplete[:50],
        "images": images, "bytes": bytes_, "spp": {str(k): v for k, v in sorted(spp.items())},
        "render_seconds": {k: round(v, 2) for k, v in render_s.items()},
        "nonfinite": nonfinite,
        "omitted_channels": dict(omitted.most_common()),
        "encodings": {f"{name}, beauty {beauty}": n for (name, beauty), n in sorted(encodings.items())},
        **({"gt": gt_summary(gt_rows)} if gt_rows else {}),
    })
    if frame is not None:
        report["frame"] = inspect_frame(store, frame)
    return report


def _gt_stats(rows: list[dict]) -> dict:
    spp = [v for g in rows for v in g["spp"].values()]
    psnr = [g["psnr_gt1_gt2"] for g in rows]
    est = [v for g in rows for v in g["estimated_psnr"].values() if v is not None]
    return {"frames": len(rows), "spp_mean": round(float(np.mean(spp)), 1), "spp_min": min(spp), "spp_max": max(spp),
            "psnr_gt1_gt2_median": round(float(np.median(psnr)), 2), "psnr_gt1_gt2_min": round(min(psnr), 2),
            "estimated_psnr_median": round(float(np.median(est)), 2) if est else None}


def gt_summary(rows: list[tuple]) -> dict:
    """Ground-truth quality over the frames whose ``frame.json`` has a ``gt`` record (the spp each GT
    reached, its estimated PSNR, the GT1-vs-GT2 PSNR): all of them and per scene family (the stress
    preset, else the split)."""
    out = _gt_stats([g for _, g in rows])
    out["by_family"] = {fam: _gt_stats([g for f, g in rows if f == fam]) for fam in sorted({f for f, _ in rows})}
    return out


def inspect_frame(store: Store, key: str) -> dict:
    try:
        scene, f = key.split("/")
        f = int(f)
    except ValueError:
        raise StoreError(f"--frame {key!r}: expected SCENE/FRAME, e.g. s00000/000") from None
    rec = store.frame_record(scene, f)
    if rec is None:
        raise StoreError(f"{store.frame_dir(scene, f)}: frame is not complete (no frame.json)")
    out = {"scene": scene, "frame": f, "timing": rec["timing"], "features": rec["features"], "images": {},
           **({"gt": rec["gt"]} if "gt" in rec else {})}
    for name in rec["images"]:
        h = store.image_header(scene, f, name)
        stored = [ch for b in h["buffers"] for ch in schema.BY_NAME[b].exr_channels + schema.BY_NAME[b].variance_channels
                  if ch not in h["constants"]]
        out["images"][name] = {"spp": h["spp"], "seed": h["seed"], "size": f"{h['width']}x{h['height']}",
                               "render_seconds": h.get("render_seconds"), "nonfinite": h.get("nonfinite", {}),
                               "estimated_psnr": h.get("estimated_psnr"), "passes": h.get("passes"),
                               "channels": stored, "constants": h["constants"],
                               "bytes": rec["images"][name].get("bytes")}
    return out


def format_report(r: dict) -> str:
    lines = [f"store {r['store']}: {r['scenes']} scenes "
             f"({', '.join(f'{k} {v}' for k, v in r['splits'].items())}), "
             f"{r['frames_complete']}/{r['frames']} frames complete, {r['images']} images, "
             f"{r['bytes'] / 2**20:.1f} MiB",
             f"  images per spp: {', '.join(f'{k} spp: {v}' for k, v in r['spp'].items())}",
             f"  render seconds: {', '.join(f'{k} {v}' for k, v in r['render_seconds'].items())}",
             f"  non-finite values repaired: {r['nonfinite']}"]
    if r.get("encodings"):
        lines.append(f"  encodings (images): {', '.join(f'{k}: {v}' for k, v in r['encodings'].items())}")
    if r["omitted_channels"]:
        top = ", ".join(f"{k} ({v})" for k, v in list(r["omitted_channels"].items())[:12])
        lines.append(f"  constant channels left out (images): {top}")
    if "gt" in r:
        lines += _format_gt(r["gt"])
    if r["incomplete"]:
        lines.append(f"  incomplete frames: {', '.join(r['incomplete'][:10])}"
                     + (" ..." if len(r["incomplete"]) > 10 else ""))
    if "frame" in r:
        fr = r["frame"]
        lines.append(f"frame {fr['scene']}/{fr['frame']:03d}: features {', '.join(fr['features'])}; "
                     f"timing {fr['timing']}")
        for name, img in fr["images"].items():
            lines.append(f"  {name}: {img['size']} {img['spp']} spp seed {img['seed']} "
                         f"{img['render_seconds']} s {img['bytes']} B; {len(img['channels'])} channels, "
                         f"{len(img['constants'])} constant; non-finite {img['nonfinite'] or 0}")
        if "gt" in fr:
            g = fr["gt"]
            lines.append(f"  ground truth: spp {g['spp']}, estimated PSNR {_db(g['estimated_psnr'])}, "
                         f"GT1 vs GT2 {_db(g['psnr_gt1_gt2'])}")
        first = next(iter(fr["images"].values()))
        lines.append(f"  channels of {next(iter(fr['images']))}: {' '.join(first['channels'])}")
        lines.append(f"  constants: {first['constants']}")
    return "\n".join(lines)


def _format_gt(g: dict) -> list[str]:
    def line(label: str, s: dict) -> str:
        return (f"{label}: {s['frames']} frames, spp {s['spp_min']}..{s['spp_max']} (mean {s['spp_mean']}), "
                f"GT1 vs GT2 PSNR median {_db(s['psnr_gt1_gt2_median'])} (min {_db(s['psnr_gt1_gt2_min'])}), "
                f"estimated PSNR median {_db(s['estimated_psnr_median'])}")
    return [line("  ground truth", g)] + [line(f"    {fam}", s) for fam, s in g["by_family"].items()]


def _db(value) -> str:
    """A recorded PSNR for people: the JSON ceiling (``PSNR_CEILING``, an exact match) reads "identical"."""
    if value is None:
        return "n/a"
    return "identical" if float(value) >= PSNR_CEILING else f"{value} dB"
