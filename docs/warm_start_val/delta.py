"""Δ (ours − oidn) per spp: mean PSNR, worst frame, Δ HDR-FLIP, for each eval folder given."""
import collections
import csv
import sys

for folder in sys.argv[1:]:
    rows = [r for r in csv.DictReader(open(f"{folder}/eval_frames.csv")) if r["status"] == "ok"]
    by = collections.defaultdict(dict)
    for r in rows:
        by[(r["group"], int(r["spp"]), r["frame"])][r["method"]] = r
    out = []
    for spp in sorted({k[1] for k in by}):
        d = [(k[2], float(v["ours"]["psnr"]) - float(v["oidn"]["psnr"]),
              float(v["ours"]["hdr_flip"]) - float(v["oidn"]["hdr_flip"]))
             for k, v in by.items() if k[1] == spp and "ours" in v and "oidn" in v]
        if not d:
            continue
        mean, hdr_flip = sum(x[1] for x in d) / len(d), sum(x[2] for x in d) / len(d)
        worst = min(d, key=lambda x: x[1])
        out.append(f"{spp}spp {mean:+.3f} (worst {worst[1]:+.2f} {worst[0]}, dHDRFLIP {hdr_flip:+.4f}, n={len(d)})")
    print("/".join(folder.rstrip("/").split("/")[-2:]) + ": " + " | ".join(out))
