"""The dataset stage: plan scenes and frames, run the missing frames, write the manifests.

``make dataset`` → ``python -m pipeline dataset``. The plan is a pure function of the config
(scene descriptions, splits, seeds), so every shard and every rerun computes the same plan and
the manifests they write are identical; only frames whose ``frame.json`` is missing are run.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from mcdenoise.pipeline import config as config_mod
from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.executors import run_tasks, task_label
from mcdenoise.pipeline.exr import StoreError
from mcdenoise.pipeline.progress import progress
from mcdenoise.pipeline.store import Store, image_names, image_seed
from mcdenoise.pipeline.versions import package_versions

# Keys that change what gets rendered: a store made with other values cannot be extended.
_FIXED_KEYS = ("seed", "dataset", "scene", "render.max_depth", "render.rr_depth", "render.features",
               "render.omit_constant")


def scene_id(index: int) -> str:
    return f"s{index:05d}"


def split_scenes(ids: list[str], val_fraction: float, test_fraction: float, seed: int) -> dict[str, list[str]]:
    """Split scene ids by scene (never by frame), deterministically from ``seed``.

    Val and test get at least one scene each when there are at least three scenes, so a tiny
    dataset still exercises every split.
    """
    n = len(ids)
    order = np.random.default_rng([seed, 0x5B117]).permutation(n)
    n_test = int(round(test_fraction * n))
    n_val = int(round(val_fraction * n))
    if n >= 3:
        n_test, n_val = max(1, n_test), max(1, n_val)
    test = sorted(ids[i] for i in order[:n_test])
    val = sorted(ids[i] for i in order[n_test:n_test + n_val])
    train = sorted(ids[i] for i in order[n_test + n_val:])
    return {"train": train, "val": val, "test": test}


@dataclasses.dataclass
class Plan:
    scenes: list[dict]        # scene manifests (static part)
    splits: dict[str, list[str]]

    def frame_tasks(self, cfg: Config) -> list:
        from .frame import FrameTask

        tasks = []
        for sm in self.scenes:
            for f in range(sm["frames"]):
                tasks.append(FrameTask(
                    store=str(cfg.store), scene=sm["scene"], frame=f, desc=sm["description"],
                    resolution=tuple(sm["resolution"]), seeds=sm["seeds"][str(f)], render=dataclasses.asdict(cfg.render),
                    **task_spp(sm)))
        return tasks


def stress_entries(presets: list[str], copies: int, first_index: int) -> list[tuple[str, int, str]]:
    """(scene id, index, preset) of every stress scene: copy 0 of a preset keeps the id ``stress_<name>``
    (so stores made before copies existed read the same), copy k > 0 is ``stress_<name>_<k>``; each has
    its own index, hence its own seed."""
    out = []
    for j, name in enumerate(presets):
        out.append((f"stress_{name}", first_index + j, name))
    for k in range(1, copies):
        for j, name in enumerate(presets):
            out.append((f"stress_{name}_{k}", first_index + k * len(presets) + j, name))
    return out


def make_plan(cfg: Config) -> Plan:
    from .scene import STRESS_PRESETS, random_scene, stress_scene

    d = cfg.dataset
    names = image_names(d.stacks)
    stress = list(STRESS_PRESETS) if d.stress == ["all"] or d.stress == "all" else list(d.stress)
    for name in stress:
        if name not in STRESS_PRESETS:
            raise config_mod.ConfigError(f"dataset.stress: unknown preset {name!r} (have {', '.join(STRESS_PRESETS)})")
    entries = [(scene_id(i), i, None) for i in range(d.scenes)]
    entries += stress_entries(stress, d.stress_copies, d.scenes)
    mixed = d.stress_split == "mixed"
    splits = split_scenes([e[0] for e in entries if mixed or e[2] is None], d.val_fraction, d.test_fraction, cfg.seed)
    splits["stress"] = [] if mixed else [e[0] for e in entries if e[2] is not None]
    split_of = {s: k for k, ids in splits.items() for s in ids}
    scenes = []
    for sid, index, preset in entries:
        desc = (random_scene(cfg.scene, cfg.seed, index, d.frames) if preset is None
                else stress_scene(preset, cfg.seed + index, d.frames))
        seeds = {str(f): {name: image_seed(cfg.seed, index, f, k, d.frames, len(names))
                          for k, name in enumerate(names)} for f in range(d.frames)}
        scenes.append(scene_record(cfg, sid, index, split_of[sid], preset, d.frames, list(d.resolution), seeds, desc))
    return Plan(scenes, splits)


def gt_settings(d: config_mod.DatasetConfig) -> dict:
    """The ground-truth keys of a scene manifest: ``gt_spp`` alone (a fixed count), or with a target
    ``gt_target_psnr``, ``gt_pass_spp`` and ``gt_spp`` = ``gt_max_spp``, the most a GT can have."""
    if d.gt_target_psnr is None:
        return {"gt_spp": d.gt_spp}
    return {"gt_spp": d.gt_max_spp, "gt_target_psnr": d.gt_target_psnr, "gt_pass_spp": d.gt_pass_spp}


def task_spp(sm: dict) -> dict:
    """The sample-count fields of a ``FrameTask`` from a scene manifest (or ``scene_record``)."""
    return {"gt_spp": sm["gt_spp"], "gt_target_psnr": sm.get("gt_target_psnr"),
            "gt_pass_spp": sm.get("gt_pass_spp", 0), "stack_spp": sm["stack_spp"], "stacks": sm["stacks"]}


def scene_record(cfg: Config, sid: str, index: int, split: str, preset: str | None, frames: int,
                 resolution: list | None, seeds: dict, desc: dict) -> dict:
    """The static part of a scene manifest (``scene.json``); see docs/store.md."""
    d = cfg.dataset
    return {
        "scene": sid, "index": index, "split": split, "preset": preset, "frames": frames,
        "resolution": resolution, **gt_settings(d), "stack_spp": d.stack_spp, "stacks": d.stacks,
        "images": image_names(d.stacks), "seeds": seeds,
        "integrator": {"type": "split", "max_depth": cfg.render.max_depth, "rr_depth": cfg.render.rr_depth,
                       "features": cfg.render.features, "filter": "box"},
        "description": desc,
    }


def _fixed_part(cfg_dict: dict) -> dict:
    out = {}
    for key in _FIXED_KEYS:
        node = cfg_dict
        for part in key.split("."):
            node = node[part]
        out[key] = node
    return out


def check_compatible(store: Store, cfg: Config) -> None:
    """Refuse to mix two configs in one store (the result would be silently inconsistent)."""
    if not store.manifest_path.exists():
        return
    old = store.manifest().get("config", {})
    try:
        old_fixed = _fixed_part(old)
    except (KeyError, TypeError):
        raise StoreError(f"{store.manifest_path}: config section is missing or incomplete") from None
    new_fixed = _fixed_part(dataclasses.asdict(cfg))
    # A key added to a section since the store was made counts as its default (old stores stay usable).
    defaults = _fixed_part(dataclasses.asdict(Config()))
    for key, value in old_fixed.items():
        if isinstance(value, dict):
            old_fixed[key] = {**defaults[key], **value}
    for key in _FIXED_KEYS:
        if old_fixed[key] != new_fixed[key]:
            raise StoreError(f"{store.manifest_path}: this store was made with a different '{key}' "
                             f"({old_fixed[key]!r}, now {new_fixed[key]!r}); use another store path")


def write_manifests(store: Store, cfg: Config, plan: Plan) -> None:
    versions = package_versions()
    # Scenes added by render-scene (split "external") survive a rerun of the dataset stage.
    external = store.manifest()["splits"].get("external", []) if store.manifest_path.exists() else []
    splits = {**plan.splits, **({"external": external} if external else {})}
    store.write_manifest({
        "config": dataclasses.asdict(cfg), "scenes": [s["scene"] for s in plan.scenes] + external,
        "splits": splits, "images": plan.scenes[0]["images"] if plan.scenes else [],
        "packages": versions,
    })
    for sm in plan.scenes:
        path = store.scene_dir(sm["scene"]) / "scene.json"
        current = store.scene_manifest(sm["scene"]) if path.exists() else {}
        static = {**sm, "packages": versions}
        if {k: current.get(k) for k in static} != static:
            store.write_scene_manifest(sm["scene"], {**current, **static})


def finalize_scene_manifests(store: Store, plan: Plan) -> None:
    """Add each finished frame's render times, bytes, non-finite counts and ground-truth record (spp
    reached, estimated PSNR, GT1-vs-GT2 PSNR) to its scene manifest."""
    for sm in plan.scenes:
        frames = {}
        for f in range(sm["frames"]):
            rec = store.frame_record(sm["scene"], f)
            if rec is not None:
                frames[str(f)] = {"timing": rec["timing"], "bytes": rec["bytes"], "nonfinite": rec["nonfinite"],
                                  "features": rec["features"],
                                  "render_seconds": {n: r.get("render_seconds") for n, r in rec["images"].items()},
                                  **({"gt": rec["gt"]} if "gt" in rec else {})}
        current = store.scene_manifest(sm["scene"])
        if current.get("rendered") != frames:
            store.write_scene_manifest(sm["scene"], {**current, "rendered": frames})


def parse_shard(text: str | None) -> tuple[int, int]:
    if not text:
        return 0, 1
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise config_mod.ConfigError(f"--shard {text!r}: expected i/N, e.g. 0/4") from None
    if not 0 <= i < n:
        raise config_mod.ConfigError(f"--shard {text!r}: need 0 <= i < N")
    return i, n


def shard_of(tasks: list, shard: tuple[int, int]) -> list:
    """Contiguous blocks, so a shard holds whole scenes where it can (scene reuse in workers)."""
    i, n = shard
    lo, hi = len(tasks) * i // n, len(tasks) * (i + 1) // n
    return tasks[lo:hi]


def run(cfg: Config, shard: str | None = None, quiet: bool = False, time_limit_s: float | None = None,
        splits: list[str] | None = None) -> dict:
    """Render the frames of ``cfg``'s plan (of one shard) that are not complete yet. ``splits``: only the frames
    of these splits, in this order (e.g. val before train). ``time_limit_s``: start no frame after that many
    seconds (frames in flight finish; a rerun renders the rest, the store stays consistent because every stage
    reads complete frames only)."""
    store = Store(cfg.store)
    check_compatible(store, cfg)
    plan = make_plan(cfg)
    write_manifests(store, cfg, plan)
    tasks = shard_of(plan.frame_tasks(cfg), parse_shard(shard))
    if splits:
        unknown = sorted(set(splits) - set(plan.splits))
        if unknown:
            raise config_mod.ConfigError(f"--splits: no split {', '.join(unknown)} (the plan has "
                                         f"{', '.join(sorted(plan.splits))})")
        order = {sid: i for i, name in enumerate(splits) for sid in plan.splits[name]}
        tasks = sorted((t for t in tasks if t.scene in order), key=lambda t: order[t.scene])   # stable: frames stay in order
    todo = [t for t in tasks if not store.is_frame_complete(t.scene, t.frame, image_names(t.stacks))]
    t0 = time.perf_counter()
    stats = {"frames": len(tasks), "skipped": len(tasks) - len(todo), "rendered": 0, "failed": 0,
             "samples": 0, "nonfinite": 0, "bytes": 0, "timing": {"build": 0.0, "render": 0.0, "write": 0.0, "total": 0.0},
             "errors": []}
    bar = progress(total=len(tasks), initial=stats["skipped"], desc="dataset", unit="frame", disable=quiet)
    for task, result, error in run_tasks(todo, render_frame_entry, cfg.executor):
        if error is not None:
            stats["failed"] += 1
            stats["errors"].append(f"{task_label(task)}: {error}")
            bar.write(f"FAILED {task_label(task)}: {error}")
        else:
            stats["rendered"] += 1
            stats["samples"] += result["samples"]
            stats["nonfinite"] += result["nonfinite"]
            stats["bytes"] += result["bytes"]
            for k in stats["timing"]:
                stats["timing"][k] += result["timing"][k]
            if result["nonfinite"]:
                bar.write(f"{task_label(task)}: repaired {result['nonfinite']} non-finite values (see inspect)")
        bar.update(1)
        if time_limit_s is not None and time.perf_counter() - t0 > time_limit_s:
            stats["stopped"] = True      # leaving the loop shuts the pool down after the frames in flight
            break
    bar.close()
    stats["wall_seconds"] = time.perf_counter() - t0
    finalize_scene_manifests(store, plan)
    stats["store_bytes"] = sum(p.stat().st_size for p in Path(cfg.store).rglob("*") if p.is_file())
    if not quiet:
        print(summary_line(stats))
    return stats


def render_frame_entry(task):
    # Module-level so that spawn workers and Ray can import it by name.
    from .frame import render_frame
    return render_frame(task)


def summary_line(stats: dict) -> str:
    wall = stats["wall_seconds"]
    rate = stats["samples"] / wall / 1e6 if wall > 0 else 0.0
    tm = stats["timing"]
    share = tm["render"] / tm["total"] * 100 if tm["total"] else 0.0
    stopped = ", stopped at the time limit" if stats.get("stopped") else ""
    return (f"dataset: {stats['frames']} frames ({stats['rendered']} rendered, {stats['skipped']} already done, "
            f"{stats['failed']} failed{stopped}) in {wall:.1f} s, {rate:.2f} M samples/s, rendering {share:.0f}% of frame time, "
            f"{stats['nonfinite']} non-finite values repaired, store {stats['store_bytes'] / 2**20:.1f} MiB")
