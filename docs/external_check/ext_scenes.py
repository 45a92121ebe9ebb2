"""Per external scene: PSNR of stock OIDN and the shipped denoiser against GT1 at 4, 16 and 64 spp.

Run from the repository root once the scenes are in the store's external split
(`make eval SCENES="configs/scenes/*.xml" store=data/external dataset.gt_spp=4096`):
``.venv/bin/python docs/external_check/ext_scenes.py [STORE]`` prints the README's table.
"""
import sys

from mcdenoise.pipeline.metrics import psnr
from mcdenoise.pipeline.store import Store
from mcdenoise.train import oidn
from mcdenoise.train.infer import load_denoiser as load_refiner
from mcdenoise.train.model import SHIPPED_MODEL


def main(store: Store) -> None:
    denoiser = load_refiner(SHIPPED_MODEL, "cpu")
    print("| scene | OIDN 4 / 16 / 64 spp | shipped - OIDN 4 / 16 / 64 spp |\n| --- | --- | --- |")
    for key in store.frames("external"):
        ref = store.read_image(key.scene, key.frame, "gt1", ["color"])[0]["color"]
        base, gain = [], []
        for spp in (4, 16, 64):
            buffers = store.read(key.scene, key.frame, spp)
            a = psnr(oidn.denoise(buffers), ref)
            base.append(f"{a:.2f}")
            gain.append(f"{psnr(denoiser.denoise(buffers, spp=spp), ref) - a:+.2f}")
        print(f"| {key.scene.removeprefix('ext_')} | {' / '.join(base)} | {' / '.join(gain)} |", flush=True)


if __name__ == "__main__":
    main(Store(sys.argv[1] if len(sys.argv) > 1 else "data/external"))
