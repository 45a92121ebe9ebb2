"""Δ (ours − oidn) per spp: mean PSNR, worst frame, Δ HDR-FLIP, for each eval folder given."""
import collections
import csv
import sys

for folder in sys.argv[1:]:
    rows = list(csv.DictReader(open(f"{folder}/eval_frames.csv")))
    by = collections.defaultdict(dict)
    for r in rows:
        if r["status"] != "ok": continue
        by[(r["group"], int(r["spp"]), r["frame"])][r["method"]] = r
    out = []
    for spp in sorted({k[1] for k in by}):
        d = [(k[2], float(v["ours"]["psnr"]) - float(v["oidn"]["psnr"]), float(v["ours"]["hdr_flip"]) - float(v["oidn"]["hdr_flip"]))
             for k, v in by.items() if k[1] == spp and "ours" in v and "oidn" in v]
        if not d: continue
        m = sum(x[1] for x in d) / len(d); hf = sum(x[2] for x in d) / len(d)
        w = min(d, key=lambda x: x[1])
        out.append(f"{spp}spp {m:+.3f} (worst {w[1]:+.2f} {w[0]}, dHDRFLIP {hf:+.4f}, n={len(d)})")
    print(folder.rstrip('/').split('/')[-2] + '/' + folder.rstrip('/').split('/')[-1] + ": " + " | ".join(out))
