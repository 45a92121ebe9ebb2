"""Frames per CPU-hour at 1 and at 8 frames per scene, from a rendered store's own timings.

    python docs/experiments/frames_per_scene.py data/ship_rooms

A scene's first frame compiles its kernels and builds its scene; its later frames reuse them. From every frame's
``frame.json`` (``timing.total``: build, render and write, wall seconds with the store's render threads on the
machine's cores), per scene kind: the mean cost of a first frame and of a later one, and what that makes of a
dataset of 1 frame per scene (every frame a first frame) and of 8 (one first frame and 7 later ones).
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np


def main(root: Path) -> int:
    manifest = json.loads((root / "dataset.json").read_text())
    render = manifest.get("config", {}).get("render", {})
    workers = int(manifest.get("config", {}).get("executor", {}).get("workers", 1) or 1)
    threads = int(render.get("threads", 0) or 0)
    cores = min(threads, os.cpu_count() / workers) if threads > 0 else os.cpu_count() / workers
    costs: dict[str, dict[str, list[float]]] = {}
    for scene_file in sorted((root / "scenes").glob("*/scene.json")):
        scene = json.loads(scene_file.read_text())
        kind = "stress" if scene.get("preset") else (scene.get("description") or {}).get("kind", "objects")
        for frame_file in sorted(scene_file.parent.glob("*/frame.json")):
            record = json.loads(frame_file.read_text())
            which = "first" if int(record["frame"]) == 0 else "later"
            costs.setdefault(kind, {"first": [], "later": []})[which].append(float(record["timing"]["total"]) * cores)
    print(f"{root}: core-seconds per frame ({cores:g} cores per render), frames per core-hour")
    print("| kind | first frames | first | later frames | later | 1 frame per scene | 8 frames per scene | ratio |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    every = {"first": [], "later": []}
    for kind, c in sorted(costs.items()) + [("all", every)]:
        if kind != "all":
            every["first"] += c["first"]
            every["later"] += c["later"]
        if not c["first"] or not c["later"]:
            continue
        first, later = float(np.mean(c["first"])), float(np.mean(c["later"]))
        one, eight = 3600 / first, 3600 * 8 / (first + 7 * later)
        print(f"| {kind} | {len(c['first'])} | {first:.1f} | {len(c['later'])} | {later:.1f} | {one:.0f} | {eight:.0f} | "
              f"{eight / one:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(Path(sys.argv[1])))
