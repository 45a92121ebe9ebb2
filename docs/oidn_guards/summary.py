"""One table row per evaluation folder: oidn_ft − oidn PSNR at 4 / 16 / 64 spp on default val, and on
the hand-made val scenes with the worst scene at 4 spp (python summary.py "NAME=FOLDER" ...)."""
import collections
import csv
import sys


def gains(folder, method="oidn_ft"):
    by = collections.defaultdict(dict)
    for r in csv.DictReader(open(f"{folder}/eval_frames.csv")):
        if r["status"] == "ok":
            by[(int(r["spp"]), r["frame"])][r["method"]] = float(r["psnr"])
    means, worst = [], None
    for spp in (4, 16, 64):
        d = [(frame, v[method] - v["oidn"]) for (s, frame), v in by.items() if s == spp]
        means.append(sum(x for _, x in d) / len(d))
        if spp == 4:
            worst = min(d, key=lambda x: x[1])
    return means, worst


for name, folder in (a.split("=", 1) for a in sys.argv[1:]):
    ext, worst = gains(f"{folder}/ext_val")
    default, _ = gains(f"{folder}/default_val")
    scene = worst[0].split("/")[0].replace("ext_val_", "")
    print(f"| {name} | " + " / ".join(f"{x:+.2f}" for x in default) + " | "
          + " / ".join(f"{x:+.2f}" for x in ext) + f" ({worst[1]:+.2f} {scene}) |")
