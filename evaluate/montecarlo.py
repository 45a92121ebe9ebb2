"""Plain Monte Carlo as a method: its convergence per frame, and the equal-time renders.

Convergence (``mc_curve``): the frame's low-spp stacks pooled 1, 2, 4, ... K at a time (the
first k stacks, 4k spp; ``Store.read`` pools them with exact statistics) and GT2 at ``gt_spp``,
an MC render independent of the reference (GT_clean is made from GT1; external scenes use GT1
itself). Each point: spp, model render seconds (``evaluate.timing``), L1 and PSNR against the
reference.

Equal time (``equal_time_images``): the image plain MC makes in a given time.

- ``render``: the frame rendered at the equal-time spp (rounded, at most
  ``eval.equal_time_max_spp``; capped rows are marked) by the dataset's own renderer
  (``render.frame``, same integrator settings as the store, in a worker process), stored next to
  the frame as ``mc<N>.exr`` (5 digits) and reused by later runs. Its measured render seconds are
  kept next to the model's.
- ``pool``: the first k stored stacks with 4k the largest multiple of the stack spp not above the
  equal-time spp, capped at all K stacks (marked).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from mcdenoise.pipeline import metrics
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.exr import StoreError
from mcdenoise.pipeline.progress import progress
from mcdenoise.pipeline.store import FrameKey, Store

from .timing import RenderCost

# Seeds of equal-time renders: the frame's GT1 seed moved by a large odd stride per spp, far from
# the consecutive counters the dataset uses (pipeline.store.image_seed).
_SEED_STRIDE = 0x632BE5AB


def mc_image_name(spp: int) -> str:
    return f"mc{int(spp):05d}"


def mc_curve(store: Store, key: FrameKey, reference: np.ndarray, cost: RenderCost,
             reference_name: str) -> list[dict]:
    sm = store.scene_manifest(key.scene)
    n, K = int(sm["stack_spp"]), int(sm["stacks"])
    counts = sorted({min(1 << i, K) for i in range(K.bit_length() + 1)})
    points = []
    for k in counts:
        # Store.read pools exactly as the methods' inputs are pooled (same stacks, same arithmetic).
        img = store.read(key.scene, key.frame, k * n, buffers=["color"], stacks=list(range(k)))["color"]
        points.append(_point(k * n, cost, img, reference, f"{k} stack{'s' if k > 1 else ''}"))
    if reference_name != "gt2" and store.image_path(key.scene, key.frame, "gt2").exists():
        gt2 = store.read_image(key.scene, key.frame, "gt2", ["color"])[0]["color"]
        # The header's spp: a progressive GT2 (dataset.gt_target_psnr) stops below the scene's gt_spp.
        spp = int(store.image_header(key.scene, key.frame, "gt2")["spp"])
        points.append(_point(spp, cost, gt2, reference, "GT2"))
    return points


def _point(spp: int, cost: RenderCost, img, ref, source: str) -> dict:
    return {"spp": int(spp), "seconds": cost.seconds(spp), "source": source,
            "l1": metrics.l1(img, ref, clamp=(0.0, 6.0)), "psnr": metrics.psnr(img, ref)}


def mean_curve(curves: dict[str, list[dict]]) -> list[dict]:
    """Points at the spp every frame has: mean seconds, L1 and PSNR over the frames."""
    if not curves:
        return []
    common = set.intersection(*({p["spp"] for p in c} for c in curves.values()))
    out = []
    for spp in sorted(common):
        pts = [next(p for p in c if p["spp"] == spp) for c in curves.values()]
        out.append({"spp": spp, **{k: float(np.mean([p[k] for p in pts])) for k in ("seconds", "l1", "psnr")}})
    return out


@dataclasses.dataclass
class EqualTime:
    spp: int                     # samples of the image used
    wanted: float                # equal-time spp before rounding / capping
    capped: bool
    image: np.ndarray | None
    measured_seconds: float | None = None   # render seconds of a rendered image
    error: str | None = None


def equal_time_images(cfg: Config, store: Store, wanted: dict[FrameKey, float], mode: str,
                      max_spp: int, quiet: bool = False) -> dict[FrameKey, EqualTime]:
    """The MC image with the equal-time sample count ``wanted[key]`` of each frame (see module doc)."""
    if mode == "pool":
        return {key: _pooled(store, key, n) for key, n in wanted.items()}
    plan = {key: min(max(1, int(round(n))), int(max_spp)) for key, n in wanted.items()}
    errors = _render_missing(cfg, store, plan, quiet)
    out = {}
    for key, n in wanted.items():
        spp = plan[key]
        capped = int(round(n)) > spp
        if key in errors:
            out[key] = EqualTime(spp, n, capped, None, error=errors[key])
            continue
        name = mc_image_name(spp)
        img = store.read_image(key.scene, key.frame, name, ["color"])[0]["color"]
        header = store.image_header(key.scene, key.frame, name)
        out[key] = EqualTime(spp, n, capped, img, header.get("render_seconds"))
    return out


def _pooled(store: Store, key: FrameKey, wanted: float) -> EqualTime:
    sm = store.scene_manifest(key.scene)
    n, K = int(sm["stack_spp"]), int(sm["stacks"])
    k = max(1, int(math.floor(wanted / n + 1e-9)))
    capped = k > K
    k = min(k, K)
    img = store.read(key.scene, key.frame, k * n, buffers=["color"], stacks=list(range(k)))["color"]
    return EqualTime(k * n, wanted, capped, img)


def _render_missing(cfg: Config, store: Store, plan: dict[FrameKey, int], quiet: bool) -> dict[FrameKey, str]:
    """Render ``mc<N>`` for every frame that lacks it, in worker processes; returns errors by frame."""
    from mcdenoise.pipeline.executors import run_tasks
    from mcdenoise.render.dataset import render_frame_entry
    from mcdenoise.render.frame import FrameTask

    tasks = []
    for key, spp in plan.items():
        name = mc_image_name(spp)
        if store.image_path(key.scene, key.frame, name).exists():
            continue
        sm = store.scene_manifest(key.scene)
        seeds = sm.get("seeds", {}).get(str(key.frame), {})
        if "gt1" not in seeds or "description" not in sm:
            raise StoreError(f"{store.scene_dir(key.scene)}: scene manifest has no description/seeds to render "
                             f"equal-time MC from; use eval.equal_time=pool")
        render = dataclasses.asdict(cfg.render)
        integ = sm.get("integrator", {})
        render.update({k: integ[k] for k in ("max_depth", "rr_depth", "features") if k in integ})
        res = sm.get("resolution")
        task = FrameTask(store=str(store.root), scene=key.scene, frame=key.frame, desc=sm["description"],
                         resolution=tuple(res) if res else None, gt_spp=int(sm["gt_spp"]), stack_spp=int(spp),
                         stacks=int(sm["stacks"]), seeds={name: (int(seeds["gt1"]) + _SEED_STRIDE * (1 + spp)) % 2**32},
                         render=render, images=[name])
        tasks.append(task)
    errors = {}
    if not tasks:
        return errors
    bar = progress(total=len(tasks), desc="equal-time MC", unit="render", disable=quiet, leave=False)
    for task, _result, error in run_tasks(tasks, render_frame_entry, cfg.executor):
        if error is not None:
            text = str(error).strip()
            errors[FrameKey(task.scene, task.frame)] = text.splitlines()[-1] if text else repr(error)
        bar.update(1)
    bar.close()
    return errors
