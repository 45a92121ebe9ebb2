"""Contact sheet of the validation scenes: GT1 colour of every ``configs/scenes/val_*.xml`` (its first sensor, the
start pose of its camera move) from a store that render-scene filled, in one labelled PNG
(``pipeline.figures.contact_sheet``).

    .venv/bin/python -m pipeline render-scene configs/scenes/val_X.xml --store /tmp/valstore dataset.gt_spp=256  # each
    .venv/bin/python -m tools.val_contact_sheet --store /tmp/valstore --out docs/figures/val_scenes.png

A scene the store does not hold is left out (and named).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from mcdenoise.pipeline.figures import contact_sheet
from mcdenoise.pipeline.store import Store

SCENES = Path(__file__).resolve().parents[1] / "configs" / "scenes"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True, help="store with ext_val_* scenes (render-scene)")
    ap.add_argument("--out", default="docs/figures/val_scenes.png")
    ap.add_argument("--cols", type=int, default=6)
    args = ap.parse_args(argv)
    store = Store(args.store)
    cells, missing = [], []
    for xml in sorted(SCENES.glob("val_*.xml")):
        sid = "ext_" + xml.stem
        if not store.image_path(sid, 0, "gt1").exists():
            missing.append(xml.name)
            continue
        cells.append((xml.stem[4:], store.read_image(sid, 0, "gt1", ["color"])[0]["color"]))
    if not cells:
        ap.error(f"--store {args.store}: holds none of the {len(missing)} validation scenes (ext_val_*: render them "
                 "with render-scene first)")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    contact_sheet(cells, Path(args.out), cols=args.cols,
                  title=f"validation scenes (GT1, start pose, gamma tonemap), {len(cells)} scenes")
    print(f"{args.out}: {len(cells)} scenes" + (f"; not in the store: {', '.join(missing)}" if missing else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
