"""A store of part of another's training frames, by links (nothing copied), for the frames-per-scene rule of
docs/experiments/ship_rooms.md.

    python docs/experiments/subset_store.py data/ship_rooms data/ship_rooms_1pf --frames-per-scene 1
    python docs/experiments/subset_store.py data/ship_rooms data/ship_rooms_8pf --frames-per-scene 8 --like data/ship_rooms_1pf

``--frames-per-scene K``: the first K frames of each train scene, over as many train scenes (in the store's
order) as it takes to hold as many frames as ``--like``'s train split (default: every train scene). The val and
test splits are the source's, whole. A frame is linked whole (its folder), a scene's ``scene.json`` is linked,
so the subset reads as the source does; the denoiser trains on the frames that have ``gt_clean``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from mcdenoise.pipeline.store import Store


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("source")
    ap.add_argument("out")
    ap.add_argument("--frames-per-scene", type=int, required=True)
    ap.add_argument("--like", default=None, help="a subset store whose number of train frames to match")
    args = ap.parse_args()
    source, out = Store(args.source), Path(args.out)
    if out.exists():
        raise SystemExit(f"error: {out}: exists; remove it or name another folder")
    k = args.frames_per_scene
    trained = [key for key in source.frames_with("train") if key.frame < k]
    budget = len(Store(args.like).frames_with("train")) if args.like else len(trained)
    keys = trained[:budget]
    scenes = list(dict.fromkeys(key.scene for key in keys))
    manifest = source.manifest()
    keep = set(scenes) | {s for split in ("val", "test") for s in manifest["splits"].get(split, [])}
    for scene in sorted(keep):
        folder = out / "scenes" / scene
        folder.mkdir(parents=True)
        (folder / "scene.json").symlink_to((source.scene_dir(scene) / "scene.json").resolve())
        frames = [key.frame for key in keys if key.scene == scene] if scene in scenes else \
            range(int(source.scene_manifest(scene)["frames"]))
        for f in frames:
            if source.frame_dir(scene, f).exists():
                (folder / source.frame_dir(scene, f).name).symlink_to(source.frame_dir(scene, f).resolve())
    manifest = {**manifest, "scenes": [s for s in manifest["scenes"] if s in keep],
                "splits": {name: [s for s in members if s in keep] for name, members in manifest["splits"].items()}}
    manifest["splits"]["train"] = scenes
    (out / "dataset.json").write_text(json.dumps(manifest, indent=1))
    print(f"{out}: {len(keys)} train frames of {len(scenes)} scenes ({k} per scene) from {source.root}, "
          f"val and test as there")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
