"""The first estimate the refine formulation starts from (``diffusion.estimate``).

    none        the noisy render itself (the paper: the diffusion model denoises from scratch)
    oidn        Intel OIDN with albedo and normal (``pipeline.oidn``)
    isik        the Isik et al. affinity network of this project (``make train MODEL=isik SPP=any``)
    oidn+isik   the mean of the two

Both are deterministic single-pass denoisers with different errors: OIDN is trained on other
people's scenes, the Isik network on ours (kernel prediction, variance-guided); their mean beat
either alone on the default validation frames (37.8 dB against 37.4 and 37.0 at 4 spp, 42.0
against 41.3 and 41.9 at 64; docs/diffusion.md). When the estimate has several components, each
is also a condition channel of the Control Module (``extra_names``), so the network can learn
where to trust which; the mean is the base's image input and the residual's origin. An input
without the renderer's variance, albedo and normal (``RENDERER_BUFFERS``: an EXR from elsewhere)
gets OIDN in place of the Isik component.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcdenoise.pipeline.exr import StoreError

KINDS = {"none": (), "oidn": ("oidn",), "isik": ("isik",), "oidn+isik": ("oidn", "isik")}
# What the Isik network (and the diffusion model, trained on the same buffers) needs beyond R, G, B: the
# renderer's per-pixel variance and the first-hit features. An EXR from elsewhere often has none of
# them; then OIDN (with albedo and normal where present) stands in for the Isik component.
RENDERER_BUFFERS = ("color.variance", "albedo", "normal")


def has_renderer_buffers(buffers: dict) -> bool:
    return all(k in buffers for k in RENDERER_BUFFERS)


def extra_names(kind: str) -> list[str]:
    """Condition channels an estimate adds: its components (model space), when it has more than one."""
    parts = KINDS[kind]
    return [f"estimate.{p}.{c}" for p in parts for c in "RGB"] if len(parts) > 1 else []


@dataclass
class Estimator:
    """``estimator(buffers) -> (estimate (H, W, 3) HDR or None, [component, ...])``."""
    kind: str = "none"
    isik: object = None          # clean.model.AffinityDenoiser, when the kind uses it
    device: str = "cpu"
    tile: int = 512

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"unknown first estimate {self.kind!r} (known: {', '.join(KINDS)})")
        if "isik" in KINDS[self.kind] and self.isik is None:
            raise ValueError(f"the first estimate {self.kind!r} needs an Isik model")

    def _component(self, name: str, buffers: dict[str, np.ndarray]) -> np.ndarray:
        if name == "oidn":
            from mcdenoise.pipeline import oidn
            return oidn.denoise(buffers)
        from mcdenoise.clean.apply import denoise
        from mcdenoise.clean.data import frame_inputs
        inputs, radiance = frame_inputs(buffers)
        return denoise(self.isik, inputs, radiance, tile=self.tile, device=self.device)

    def __call__(self, buffers: dict[str, np.ndarray]) -> tuple[np.ndarray | None, list[np.ndarray]]:
        names = [p if has_renderer_buffers(buffers) else "oidn" for p in KINDS[self.kind]]
        done = {p: self._component(p, buffers) for p in dict.fromkeys(names)}   # each method once
        parts = [done[p] for p in names]
        if not parts:
            return None, []
        return np.mean(parts, axis=0).astype(np.float32), parts


def load(kind: str, isik_folder: str | Path | None, device: str = "cpu") -> Estimator:
    """The estimator of ``kind``; the Isik network from ``isik_folder`` when the kind needs it."""
    if kind not in KINDS:
        raise StoreError(f"diffusion.estimate: unknown first estimate {kind!r} (known: {', '.join(KINDS)})")
    isik = None
    if "isik" in KINDS[kind]:
        from mcdenoise.clean.model import load_model
        folder = Path(isik_folder) if isik_folder else None
        if folder is None or not (folder / "model.safetensors").exists():
            raise StoreError(f"the first estimate {kind!r} needs a trained Isik network: none in {folder} "
                             "(run `make train MODEL=isik SPP=any`, or set diffusion.isik_run)")
        isik = load_model(folder, device)[0]
    return Estimator(kind, isik, str(device))
