"""``make bench``: the dataset stage's performance claims, measured in one run.

1. Our split-buffer integrator against Mitsuba's built-in ``path`` on the same scenes, spp and
   max depth: time per sample as a ratio (target <= 1.15x), with every feature and with the
   features the scene needs.
2. Where the dataset stage's wall time goes: rendering vs building scenes, writing EXR and the
   rest (start-up, planning, manifests), on a few frames of the configured dataset.
3. What leaving out unneeded and constant channels saves: bytes on disk (the same rendered
   buffers written with and without omission) and render time (features 'auto' vs 'all').

Results go to ``<out>/bench.json`` and ``<out>/bench.md``; the Markdown is also printed.
"""
from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile
import time
from pathlib import Path

from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.store import Store
from mcdenoise.pipeline.timing import best_time
from mcdenoise.pipeline.versions import machine, package_versions


def integrator_vs_path(cfg: Config, resolution: int = 256, spp: int = 64, repeats: int = 3) -> list[dict]:
    import drjit as dr

    from mcdenoise.pipeline.mitsuba_env import import_mitsuba

    from .buffers import make_sensor, needed_features, render_image
    from .scene import build_scene, random_scene

    mi = import_mitsuba(cfg.render.variant, cfg.render.threads)
    rows = []
    cases = [("cornell_box", mi.load_dict(mi.cornell_box()), None)]
    desc = random_scene(cfg.scene, cfg.seed, 0, 1)
    cases.append(("random scene 0", build_scene(mi, desc), desc))
    for name, scene, desc in cases:
        if desc is None:
            sensor = make_sensor(mi, mi.ScalarTransform4f().look_at(origin=[0, 0, 3.9], target=[0, 0, 0], up=[0, 1, 0]),
                                 39.3, resolution, resolution)
        else:
            from .scene import build_sensor
            sensor = build_sensor(mi, desc, 0, resolution, resolution)
        path = mi.load_dict({"type": "path", "max_depth": cfg.render.max_depth, "rr_depth": cfg.render.rr_depth})

        def run_path():
            dr.eval(mi.render(scene, sensor=sensor, integrator=path, spp=spp, seed=1))
            dr.sync_thread()

        def run_ours(features):
            return lambda: render_image(mi, scene, sensor, spp=spp, seed=1, features=features,
                                        max_depth=cfg.render.max_depth, rr_depth=cfg.render.rr_depth)

        from mcdenoise.pipeline import schema
        needed = needed_features(mi, scene)
        for fn in (run_path, run_ours(set(schema.OPTIONAL_FEATURES)), run_ours(needed)):
            fn()  # warm-up: kernel compilation is not what we compare
        t_path = best_time(run_path, repeats)
        t_all = best_time(run_ours(set(schema.OPTIONAL_FEATURES)), repeats)
        t_needed = best_time(run_ours(needed), repeats)
        samples = resolution * resolution * spp
        rows.append({"scene": name, "resolution": resolution, "spp": spp, "path_s": t_path,
                     "ours_all_s": t_all, "ours_needed_s": t_needed, "needed_features": sorted(needed),
                     "ratio_all": t_all / t_path, "ratio_needed": t_needed / t_path,
                     "path_msamples_per_s": samples / t_path / 1e6})
    return rows


def compile_vs_render(cfg: Config, scenes: int = 3, frames: int = 2, images: tuple = ("gt1", "s00")) -> dict:
    """Per frame of the configured dataset (its resolution, spp and scenes, ``frames`` camera views each): seconds
    drjit spends compiling kernels (its kernel history: code generation and the backend's compilation, LLVM on
    the CPU, OptiX/CUDA on a GPU) against seconds rendering, for a scene's first frame and its later ones.
    A new random scene compiles its one megakernel again; later frames of the scene reuse it. Then the first
    frame of each scene once more with its material and light values changed a little (``revalued``): the
    frames that compile again show the values Mitsuba compiles in."""
    import drjit as dr
    import numpy as np

    from mcdenoise.pipeline.mitsuba_env import import_mitsuba

    from .dataset import make_plan
    from .frame import frame_scene, frame_sensor, render_one

    sub = dataclasses.replace(cfg, seed=cfg.seed + 7919,   # scenes whose kernels no earlier run cached on disk
                              dataset=dataclasses.replace(cfg.dataset, scenes=scenes, frames=frames, stress=[]))
    mi = import_mitsuba(sub.render.variant, sub.render.threads)
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    rows = []

    def timed(task, kind):
        scene, features, _ = frame_scene(mi, task)
        sensor = frame_sensor(mi, task, scene)
        dr.kernel_history()                              # empties it
        t0 = time.perf_counter()
        for name in images:
            render_one(mi, scene, sensor, task, name, features)
        wall = time.perf_counter() - t0
        kernels = [k for k in dr.kernel_history() if "hash" in k]
        compile_s = sum(k.get("codegen_time", 0.0) + k.get("backend_time", 0.0) for k in kernels) / 1000
        rows.append({"scene": task.scene, "frame": task.frame, "kind": kind, "wall_s": wall, "compile_s": compile_s,
                     "render_s": wall - compile_s, "kernels": len(kernels),
                     "compiled": sum(not k.get("cache_hit") for k in kernels)})
    try:
        tasks = make_plan(sub).frame_tasks(sub)
        for task in tasks:
            timed(task, "first" if task.frame == 0 else "later")
        # The first frame of each scene again, every material and light value changed by up to 5 %: whatever
        # compiles now was compiled in for those values (the scene's structure and geometry are the same).
        for task in tasks:
            if task.frame == 0:
                timed(dataclasses.replace(task, desc=revalued(task.desc, np.random.default_rng(task.seeds["gt1"]))),
                      "revalued")
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)

    def mean(rs, key):
        return sum(r[key] for r in rs) / len(rs) if rs else float("nan")
    out = {"images": list(images), "rows": rows}
    for kind in ("first", "later", "revalued"):
        rs = [r for r in rows if r["kind"] == kind]
        out.update({f"{k}_{kind}": mean(rs, k) for k in ("compile_s", "render_s")})
        out[f"compiled_scenes_{kind}"] = sum(r["compiled"] > 0 for r in rs)
        out[f"scenes_{kind}"] = len(rs)
    return out


def revalued(desc: dict, rng) -> dict:
    """``desc`` with every float of its materials, lights and environment scaled by a factor in [0.95, 1.05]
    (colours, texture palettes, roughness, index of refraction, light strengths and sizes); its structure,
    geometry and camera unchanged."""
    def walk(x):
        if isinstance(x, dict):
            return {k: walk(v) for k, v in x.items()}
        if isinstance(x, list):
            return [walk(v) for v in x]
        return x * float(rng.uniform(0.95, 1.05)) if isinstance(x, float) else x

    out = dict(desc)
    out["objects"] = [{**o, "material": walk(o["material"])} for o in desc.get("objects", [])]
    if desc.get("ground"):
        out["ground"] = {**desc["ground"], "material": walk(desc["ground"]["material"])}
    out["walls"] = [{**w, "material": walk(w["material"])} for w in desc.get("walls", [])]
    out["lights"] = walk(desc.get("lights", []))
    out["environment"] = walk(desc.get("environment"))
    return out


def dataset_shares(cfg: Config, scenes: int) -> dict:
    """Run the dataset stage on ``scenes`` scenes into a temporary store and split its wall time."""
    from .dataset import run

    tmp = Path(tempfile.mkdtemp(prefix="bench-store-"))
    try:
        sub = dataclasses.replace(cfg, store=str(tmp / "store"),
                                  dataset=dataclasses.replace(cfg.dataset, scenes=scenes, stress=[]))
        t0 = time.perf_counter()
        stats = run(sub, quiet=True)
        wall = time.perf_counter() - t0
        tm = stats["timing"]
        return {"scenes": scenes, "frames": stats["frames"], "wall_s": wall, "gt": gt_quality(Store(sub.store)),
                "render_share": tm["render"] / wall, "build_share": tm["build"] / wall,
                "write_share": tm["write"] / wall,
                "rest_share": 1 - (tm["render"] + tm["build"] + tm["write"]) / wall,
                "msamples_per_s": stats["samples"] / wall / 1e6}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def gt_quality(store: Store) -> dict:
    """Ground truths of a rendered store: mean spp reached, GT render seconds, GT1-vs-GT2 PSNR median/min."""
    import numpy as np

    spp, seconds, psnr = [], 0.0, []
    for key in store.frames():
        rec = store.frame_record(key.scene, key.frame)
        if rec is None or "gt" not in rec:
            continue   # a failed frame (reported by the dataset stage)
        for name in ("gt1", "gt2"):
            spp.append(rec["images"][name]["spp"])
            seconds += rec["images"][name].get("render_seconds") or 0.0
        psnr.append(rec["gt"]["psnr_gt1_gt2"])
    if not psnr:
        return {"spp_mean": float("nan"), "render_s": 0.0, "psnr_gt1_gt2_median": float("nan"),
                "psnr_gt1_gt2_min": float("nan")}
    return {"spp_mean": float(np.mean(spp)), "render_s": seconds, "psnr_gt1_gt2_median": float(np.median(psnr)),
            "psnr_gt1_gt2_min": float(np.min(psnr))}


def omission_savings(cfg: Config, timing_spp: int = 128) -> dict:
    """Bytes of the rendered store vs the same buffers with every channel written.

    Re-renders frame 0 of every scene at ``timing_spp`` with the needed features and with all
    of them, to measure the render-time saving of computing only what the scene needs.
    """
    from mcdenoise.pipeline import schema
    from mcdenoise.pipeline.exr import read_image, write_image
    from mcdenoise.pipeline.mitsuba_env import import_mitsuba

    from .buffers import needed_features, render_image
    from .scene import build_scene, build_sensor
    store = Store(cfg.store)
    omitted = full = images = 0
    t_auto = t_all = 0.0
    tmp = Path(tempfile.mkdtemp(prefix="bench-full-"))
    mi = import_mitsuba(cfg.render.variant, cfg.render.threads)
    try:
        for scene in store.scenes():
            sm = store.scene_manifest(scene)
            if "xml" in sm["description"]:
                continue  # external scenes: not part of the dataset's savings
            for f in range(sm["frames"]):
                for name in sm["images"]:
                    path = store.image_path(scene, f, name)
                    images += 1
                    omitted += path.stat().st_size
                    arrays, rec = read_image(path)
                    write_image(tmp / "full.exr", arrays, omit_constant=False)
                    full += (tmp / "full.exr").stat().st_size
            mscene = build_scene(mi, sm["description"])
            w, h = sm["resolution"]
            sensor = build_sensor(mi, sm["description"], 0, w, h)
            needed = needed_features(mi, mscene)
            for features in (needed, set(schema.OPTIONAL_FEATURES)):  # warm both kernels
                render_image(mi, mscene, sensor, spp=sm["stack_spp"], seed=0, features=features,
                             max_depth=cfg.render.max_depth, rr_depth=cfg.render.rr_depth)
            spp = min(sm["gt_spp"], timing_spp)
            t_auto += render_image(mi, mscene, sensor, spp=spp, seed=1, features=needed,
                                   max_depth=cfg.render.max_depth, rr_depth=cfg.render.rr_depth).seconds
            t_all += render_image(mi, mscene, sensor, spp=spp, seed=1, features=set(schema.OPTIONAL_FEATURES),
                                  max_depth=cfg.render.max_depth, rr_depth=cfg.render.rr_depth).seconds
            del mscene
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"store": str(cfg.store), "images": images, "timing_spp": timing_spp,
            "bytes_omitted": omitted, "bytes_full": full, "disk_saving": 1 - omitted / full,
            "render_s_needed": t_auto, "render_s_all": t_all, "time_saving": 1 - t_auto / t_all}


def run_bench(cfg: Config, out: str = "reports/bench", scenes: int = 4, resolution: int = 256, spp: int = 64,
              repeats: int = 3) -> dict:
    result = {"machine": machine(),
              "packages": package_versions(),
              "integrator": integrator_vs_path(cfg, resolution, spp, repeats),
              "dataset": dataset_shares(cfg, scenes),
              "compile": compile_vs_render(cfg, scenes=min(scenes, 3))}
    # Savings are measured on the configured store (the default dataset after `make dataset`);
    # without one, on a store of `scenes` scenes rendered for the purpose.
    if Store(cfg.store).manifest_path.exists():
        result["omission"] = omission_savings(cfg)
    else:
        tmp = Path(tempfile.mkdtemp(prefix="bench-store-"))
        try:
            sub = dataclasses.replace(cfg, store=str(tmp / "store"),
                                      dataset=dataclasses.replace(cfg.dataset, scenes=scenes, stress=[]))
            from .dataset import run
            run(sub, quiet=True)
            result["omission"] = omission_savings(sub)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "bench.json").write_text(json.dumps(result, indent=1) + "\n")
    md = format_markdown(result, cfg)
    (out_dir / "bench.md").write_text(md)
    print(md)
    return result


def format_markdown(r: dict, cfg: Config) -> str:
    lines = ["# Benchmark", "", f"Machine: {r['machine']['cpus']} CPUs, {r['machine']['platform']}; "
             f"mitsuba {r['packages']['mitsuba']}, drjit {r['packages']['drjit']}, variant {cfg.render.variant}.", "",
             "## Split-buffer integrator vs built-in `path` (best of 3, after warm-up)", "",
             "| scene | size | spp | path s | ours (all features) s | ratio | ours (needed features) s | ratio |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in r["integrator"]:
        lines.append(f"| {row['scene']} | {row['resolution']}² | {row['spp']} | {row['path_s']:.3f} | "
                     f"{row['ours_all_s']:.3f} | {row['ratio_all']:.2f}x | {row['ours_needed_s']:.3f} | "
                     f"{row['ratio_needed']:.2f}x |")
    d = r["dataset"]
    g = d["gt"]
    o = r["omission"]
    lines += ["", f"## Dataset stage wall time ({d['scenes']} scenes, {d['frames']} frames of the configured dataset)", "",
              "| rendering | building scenes | writing EXR | rest | wall s | M samples/s |",
              "| --- | --- | --- | --- | --- | --- |",
              f"| {d['render_share']:.1%} | {d['build_share']:.1%} | {d['write_share']:.1%} | {d['rest_share']:.1%} | "
              f"{d['wall_s']:.1f} | {d['msamples_per_s']:.2f} |", "",
              f"Ground truths ({_gt_rule(cfg)}): {g['spp_mean']:.0f} spp on average, {g['render_s']:.1f} s of GT "
              f"rendering, GT1 vs GT2 PSNR median {g['psnr_gt1_gt2_median']:.2f} dB (min {g['psnr_gt1_gt2_min']:.2f}).", "",
              *_compile_lines(r["compile"], cfg),
              f"## Leaving out what a scene does not need (store {o['store']}, {o['images']} images)", "",
              f"- disk: {o['bytes_omitted'] / 2**20:.2f} MiB with omission vs {o['bytes_full'] / 2**20:.2f} MiB with every "
              f"channel written: {o['disk_saving']:.1%} saved",
              f"- render time at {o['timing_spp']} spp, frame 0 of every scene: {o['render_s_needed']:.2f} s with the needed features vs "
              f"{o['render_s_all']:.2f} s with all: {o['time_saving']:.1%} saved", ""]
    return "\n".join(lines)


def _compile_lines(c: dict, cfg: Config) -> list[str]:
    d = cfg.dataset
    return [f"## Kernel compilation against rendering, per frame ({', '.join(c['images'])} of "
            f"{d.resolution[0]}x{d.resolution[1]} frames, variant {cfg.render.variant})", "",
            "| frame | compiling s | rendering s | frames that compiled |", "| --- | ---: | ---: | ---: |",
            *(f"| {label} | {c['compile_s_' + kind]:.2f} | {c['render_s_' + kind]:.2f} | "
              f"{c['compiled_scenes_' + kind]} of {c['scenes_' + kind]} |" for label, kind in KINDS), "",
            "A new random scene compiles its megakernel again; the other frames of a scene reuse it "
            "(`dataset.frames` above 1 spreads one compilation over several camera views). The same scene with "
            "its material and light values changed by a few percent compiles again where Mitsuba inlines "
            "plugin values as constants (RGB reflectances, index of refraction, roughness, emitter "
            "parameters): scenes share a kernel only where they share those values as well as their structure.", ""]


KINDS = (("first frame of a scene", "first"), ("later frame of a scene", "later"),
         ("first frame, material and light values ×[0.95, 1.05]", "revalued"))


def _gt_rule(cfg: Config) -> str:
    d = cfg.dataset
    if d.gt_target_psnr is None:
        return f"fixed {d.gt_spp} spp"
    return f"target {d.gt_target_psnr:g} dB, passes of {d.gt_pass_spp}, cap {d.gt_max_spp}"
