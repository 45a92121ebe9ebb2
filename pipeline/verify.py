"""``python -m pipeline verify STORE [--jobs N] [--headers-only]``: check every file of a store;
exit 1 on any problem.

What is checked (each problem is reported as ``PATH: what is wrong``):

- ``dataset.json``: readable, valid (``Store.manifest``), every scene in exactly one split, no
  scene folder on disk that the manifest does not list.
- ``scene.json`` of each scene: readable, valid counts, images, resolution.
- every frame: ``frame.json`` present (else the frame is incomplete), naming this scene and
  frame, listing exactly the scene's images, with totals (bytes, samples, non-finite counts)
  that add up.
- every image: present; size and SHA-256 equal to ``frame.json``'s record; the header record
  equal to that record; the size the scene's resolution; the spp and seed the scene's; every
  schema buffer present, each channel stored or a recorded constant, never both; and (unless
  ``--headers-only``) the pixels decoded: storage types per schema (float32 radiance and
  variance), the header checksum, every value finite, the header's repaired non-finite counts
  equal to ``frame.json``'s.
- the image's encoding (``pipeline.exr``): a version 3 or 4 (compact) image is ZIP- or
  ZSTD-compressed, names a known encoding, derives the beauty only when it lists all its components,
  stores R, G, B as the record says (version 4 ``view``: half, equal bit for bit to the half view of
  the derived beauty; ``stored``: float32; version 3 ``sum``: none) (the reader checks that), and
  (with pixels) holds variances and depth with no more mantissa bits than its record states;
  version 1 and 2 (exact) images are ZIP-compressed.
- ``gt_clean.exr``: made by the cleaner that ``cleaner.json`` names (header ``cleaner_sha256``),
  listed there, the frame's size; ``cleaner.json``'s checkpoint, where it still exists, has that
  hash; no gt_clean without a cleaner.json.
- leftovers: temporary files (``.*.tmp``, from an interrupted write) and unexpected files.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import schema
from .exr import StoreError, read_header, read_image, read_json
from .store import Store, frame_name, sha256

CLEANER_MANIFEST = "cleaner.json"
# Keys of an image's frame.json record that the header does not carry.
RECORD_ONLY = {"bytes", "sha256", "reused"}


@dataclass
class Report:
    root: Path
    problems: list[str] = field(default_factory=list)
    scenes: int = 0
    frames: int = 0
    incomplete: int = 0
    images: int = 0
    bytes: int = 0

    def add(self, path, message: str) -> None:
        self.problems.append(f"{path}: {message}")

    def merge(self, other: "Report") -> None:
        self.problems += other.problems
        for key in ("scenes", "frames", "incomplete", "images", "bytes"):
            setattr(self, key, getattr(self, key) + getattr(other, key))

    def summary(self, seconds: float, pixels: bool) -> str:
        what = "headers, pixels and checksums" if pixels else "headers only"
        return (f"verify {self.root}: {self.scenes} scenes, {self.frames} frames ({self.incomplete} incomplete), "
                f"{self.images} images, {self.bytes / 2**20:.1f} MiB checked ({what}) in {seconds:.1f} s: "
                f"{len(self.problems)} problem{'s' if len(self.problems) != 1 else ''}")


def verify_store(root: str | Path, pixels: bool = True, jobs: int = 1) -> Report:
    """Check the whole store; ``jobs`` > 1 checks scenes in that many worker processes."""
    store = Store(root)
    report = Report(Path(root))
    if not store.root.is_dir():
        report.add(store.root, "store folder does not exist")
        return report
    try:
        manifest = store.manifest()
    except StoreError as exc:
        report.problems.append(str(exc))
        _leftovers(store.root, report, None, recursive=True)
        return report
    _check_splits(store, manifest, report)
    cleaner = _cleaner_manifest(store, report)
    args = [(str(store.root), scene, cleaner, pixels) for scene in manifest["scenes"]]
    if jobs > 1 and len(args) > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor
        with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            parts = list(pool.map(_verify_scene, args, chunksize=max(1, len(args) // (8 * jobs))))
    else:
        parts = [_verify_scene(a) for a in args]
    for part in parts:
        report.merge(part)
    if cleaner is not None:
        _check_cleaner_frames(store, cleaner, report)
    # Top level: only the manifests; every listed scene folder was checked by its worker.
    _leftovers(store.root, report, {store.manifest_path, store.root / CLEANER_MANIFEST}, recursive=False)
    scenes_dir = store.root / "scenes"
    if scenes_dir.is_dir():
        _leftovers(scenes_dir, report, set(), recursive=False)   # unlisted scene folders: _check_splits
    return report


def _verify_scene(args) -> Report:
    root, scene, cleaner, pixels = args
    store = Store(root)
    report = Report(store.root)
    report.scenes = 1
    try:
        sm = store.scene_manifest(scene)
    except StoreError as exc:
        report.problems.append(str(exc))
        return report
    known: set[Path] = {store.scene_dir(scene) / "scene.json"}
    for f in range(sm["frames"]):
        report.frames += 1
        _check_frame(store, scene, f, sm, cleaner, report, known, pixels)
    _leftovers(store.scene_dir(scene), report, known, recursive=True)
    return report


def _check_splits(store: Store, manifest: dict, report: Report) -> None:
    seen: dict[str, str] = {}
    for split, ids in manifest["splits"].items():
        for sid in ids:
            if sid in seen:
                report.add(store.manifest_path, f"scene {sid!r} is in splits {seen[sid]!r} and {split!r}")
            seen[sid] = split
    for sid in manifest["scenes"]:
        if sid not in seen:
            report.add(store.manifest_path, f"scene {sid!r} is in no split")
    for sid in seen:
        if sid not in manifest["scenes"]:
            report.add(store.manifest_path, f"split {seen[sid]!r} lists scene {sid!r}, which 'scenes' does not")
    scenes_dir = store.root / "scenes"
    if scenes_dir.is_dir():
        for d in sorted(scenes_dir.iterdir()):
            if d.is_dir() and d.name not in manifest["scenes"]:
                report.add(d, "scene folder is not listed in dataset.json")


def _cleaner_manifest(store: Store, report: Report) -> dict | None:
    path = store.root / CLEANER_MANIFEST
    if not path.exists():
        return None
    try:
        data = read_json(path, "cleaner manifest")
    except StoreError as exc:
        report.problems.append(str(exc))
        return None
    if not isinstance(data.get("sha256"), str) or not isinstance(data.get("frames"), dict):
        report.add(path, "needs 'sha256' (the cleaner checkpoint's hash) and 'frames'")
        return None
    ckpt = data.get("checkpoint")
    if isinstance(ckpt, str) and Path(ckpt).is_file() and sha256(Path(ckpt)) != data["sha256"]:
        report.add(path, f"the checkpoint {ckpt} changed since gt_clean was written (hash differs); "
                         f"rerun make gt-clean")
    return data


def _check_frame(store: Store, scene: str, f: int, sm: dict, cleaner: dict | None, report: Report,
                 known: set, pixels: bool) -> None:
    fdir = store.frame_dir(scene, f)
    fpath = fdir / "frame.json"
    try:
        rec = store.frame_record(scene, f)
    except StoreError as exc:
        report.problems.append(str(exc))
        return
    known.add(fpath)
    images = list(sm.get("images") or [])
    if rec is None:
        report.incomplete += 1
        again = "python -m pipeline render-scene" if sm.get("split") == "external" else "make dataset"
        report.add(fdir, f"frame is incomplete (no frame.json); rerun {again}")
        known.update(fdir / f"{n}.exr" for n in images)
        return
    if rec.get("scene") not in (None, scene) or rec.get("frame") not in (None, f):
        report.add(fpath, f"names frame {rec.get('scene')}/{rec.get('frame')}, expected {scene}/{f}")
    listed = rec["images"]
    if images and sorted(listed) != sorted(images):
        report.add(fpath, f"lists images {sorted(listed)}, scene.json expects {sorted(images)}")
    res = sm.get("resolution")
    size = tuple(res) if res else (rec.get("width"), rec.get("height"))
    nonfinite = 0
    for name, img in listed.items():
        path = store.image_path(scene, f, name)
        known.add(path)
        nonfinite += _check_image(store, path, name, img, sm, f, size, report, pixels)
    if isinstance(rec.get("bytes"), int) and rec["bytes"] != sum(int(i.get("bytes", 0)) for i in listed.values()):
        report.add(fpath, f"total bytes {rec['bytes']} is not the sum of its images' bytes")
    if "nonfinite" in rec and rec["nonfinite"] != nonfinite:
        report.add(fpath, f"counts {rec['nonfinite']} repaired non-finite values, the image headers {nonfinite}")
    if "samples" in rec and None not in size:
        expected = size[0] * size[1] * sum(int(i.get("spp", 0)) for i in listed.values())
        if rec["samples"] != expected:
            report.add(fpath, f"counts {rec['samples']} samples, its images add up to {expected}")
    clean = store.image_path(scene, f, "gt_clean")
    if clean.exists():
        known.add(clean)
        _check_gt_clean(clean, f"{scene}/{frame_name(f)}", cleaner, size, report, pixels)


def _check_image(store: Store, path: Path, name: str, img: dict, sm: dict, f: int, size: tuple,
                 report: Report, pixels: bool) -> int:
    """Checks one dataset image; returns the header's repaired non-finite count."""
    report.images += 1
    if not path.exists():
        report.add(path, "image listed in frame.json is missing")
        return 0
    nbytes = path.stat().st_size
    report.bytes += nbytes
    if img.get("bytes") != nbytes:
        report.add(path, f"file has {nbytes} bytes, frame.json records {img.get('bytes')}")
    if pixels and "sha256" in img and sha256(path) != img["sha256"]:
        report.add(path, "SHA-256 differs from frame.json's: the file changed or is damaged")
    try:
        arrays, header = read_image(path) if pixels else (None, read_header(path))
    except StoreError as exc:
        report.problems.append(str(exc))
        return 0
    for key, value in header.items():
        if key not in RECORD_ONLY and img.get(key) != value:
            report.add(path, f"header {key!r} is {value!r}, frame.json records {img.get(key)!r}")
    if (header["width"], header["height"]) != size:
        report.add(path, f"image is {header['width']}x{header['height']}, the scene's frames are {size[0]}x{size[1]}")
    spp = sm["gt_spp"] if name.startswith("gt") else sm["stack_spp"]
    allowed, says = [spp], f"{spp}"
    if name.startswith("gt") and sm.get("gt_target_psnr") is not None:   # progressive: whole passes up to gt_spp
        step = sm.get("gt_pass_spp") if type(sm.get("gt_pass_spp")) is int and sm["gt_pass_spp"] > 0 else spp + 1
        allowed, says = range(step, spp + 1, step), f"a multiple of gt_pass_spp {sm.get('gt_pass_spp')!r} up to {spp}"
    if "spp" in header and header["spp"] not in allowed:
        report.add(path, f"rendered at {header['spp']} spp, scene.json says {says}")
    seed = (sm.get("seeds") or {}).get(str(f), {}).get(name)
    if seed is not None and header.get("seed") != seed:
        report.add(path, f"seed {header.get('seed')}, scene.json says {seed}")
    missing = [b.name for b in schema.BUFFERS if b.name not in header["buffers"]]
    if missing:
        report.add(path, f"buffers {', '.join(missing)} are missing")
    _check_channels(path, header, report)
    _check_encoding(path, header, arrays, report)
    if arrays is not None:
        for key, arr in arrays.items():
            bad = int(np.count_nonzero(~np.isfinite(arr)))
            if bad:
                report.add(path, f"buffer {key!r} has {bad} non-finite values (the writer repairs and counts them)")
    counts = header.get("nonfinite") or {}
    return int(sum(counts.values())) if isinstance(counts, dict) else 0


def _check_channels(path: Path, header: dict, report: Report) -> None:
    from .exr import scan_exr
    stored = set(scan_exr(path)["channels"])
    both = sorted(stored & set(header.get("constants", {})))
    if both:
        report.add(path, f"channels {', '.join(both)} are stored and also recorded as constants")


def _check_encoding(path: Path, header: dict, arrays: dict | None, report: Report) -> None:
    """Compression as the record's encoding says; stored variances/depth within its mantissa bits."""
    from .exr import COMPRESSIONS, encoding_of, scan_exr
    # read_image/read_header checked a version 3 record's encoding; older images are all exact.
    encoding = encoding_of(header)["name"]
    compression = scan_exr(path)["compression"]
    if compression not in COMPRESSIONS[encoding]:
        report.add(path, f"{encoding} image compressed with {compression}, expected {' or '.join(COMPRESSIONS[encoding])}")
    bits = header["encoding"].get("mantissa_bits") if encoding == "compact" else None
    if arrays is None or encoding != "compact":
        return
    if not isinstance(bits, dict):
        report.add(path, f"encoding record's mantissa_bits is {bits!r}, expected {{'variance': n, 'depth': n}}")
        return
    for key, arr in arrays.items():
        kind = "variance" if key.endswith(".variance") else key if key == "depth" else None
        if kind is None:
            continue
        if not isinstance(bits.get(kind), int) or not 0 <= bits[kind] <= 23:
            report.add(path, f"encoding record states no mantissa bits for {kind} (expected 0..23)")
            continue
        extra = np.count_nonzero(arr.view(np.uint32) & np.uint32((1 << (23 - bits[kind])) - 1))
        if extra:
            report.add(path, f"buffer {key!r} has {extra} values with more than the {bits[kind]} mantissa bits "
                             f"its encoding states")


def _check_gt_clean(path: Path, key: str, cleaner: dict | None, size: tuple, report: Report, pixels: bool) -> None:
    report.images += 1
    report.bytes += path.stat().st_size
    try:
        header = read_image(path)[1] if pixels else read_header(path)
    except StoreError as exc:
        report.problems.append(str(exc))
        return
    if (header["width"], header["height"]) != size:
        report.add(path, f"gt_clean is {header['width']}x{header['height']}, the frame is {size[0]}x{size[1]}")
    made_by = header.get("cleaner_sha256")
    if cleaner is None:
        report.add(path, f"gt_clean exists but the store has no {CLEANER_MANIFEST}; rerun make gt-clean")
    elif made_by != cleaner["sha256"]:
        report.add(path, f"made by cleaner {str(made_by)[:12]}, {CLEANER_MANIFEST} names {cleaner['sha256'][:12]}; "
                         f"rerun make gt-clean")
    elif cleaner["frames"].get(key) != made_by:
        report.add(path, f"{CLEANER_MANIFEST} does not list this frame as made by {made_by[:12]}")


def _check_cleaner_frames(store: Store, cleaner: dict, report: Report) -> None:
    for key in cleaner["frames"]:
        try:
            scene, f = key.split("/")
            path = store.image_path(scene, int(f), "gt_clean")
        except (ValueError, StoreError):
            report.add(store.root / CLEANER_MANIFEST, f"frame key {key!r} is not SCENE/FRAME")
            continue
        if not path.exists():
            report.add(path, f"listed in {CLEANER_MANIFEST} but missing")


def _leftovers(folder: Path, report: Report, known: set | None, recursive: bool) -> None:
    """Temporary files, and (where ``known`` is given) files nobody expects, in ``folder``."""
    for path in sorted(folder.rglob("*") if recursive else folder.iterdir()):
        if not path.is_file():
            continue
        if path.name.endswith(".tmp"):
            report.add(path, "temporary file left by an interrupted write (delete it, or rerun the stage)")
        elif known is not None and path not in known:
            report.add(path, "unexpected file in the store")


# ---- bytes per channel group (``verify STORE --bytes N``; the table in docs/store.md) -----------------

GROUPS = ("beauty", "beauty variance", "radiance components", "component variances", "features (half)", "depth",
          "feature variances")


def channel_group(channel: str) -> str:
    """The ``GROUPS`` entry of a schema EXR channel."""
    buf, _, is_var = schema.exr_channel_map()[channel]
    if buf == "color":
        return GROUPS[1] if is_var else GROUPS[0]
    if schema.BY_NAME[buf].radiance:
        return GROUPS[3] if is_var else GROUPS[2]
    return GROUPS[6] if is_var else GROUPS[5] if buf == "depth" else GROUPS[4]


def group_bytes(path: Path) -> dict[str, int]:
    """Bytes of each channel group of an image: the group's stored channels written alone with the
    image's compression (each with its own header and chunk overhead, so the groups add up to a
    few % more than the file)."""
    import tempfile

    import OpenEXR

    from .exr import scan_exr
    compression = getattr(OpenEXR, f"{scan_exr(path)['compression']}_COMPRESSION")
    with OpenEXR.File(str(path), separate_channels=True) as f:
        channels = {name: ch.pixels.copy() for name, ch in f.channels().items()}
    groups: dict[str, dict] = {}
    for name, pixels in channels.items():
        groups.setdefault(channel_group(name), {})[name] = pixels
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for group, part in groups.items():
            with OpenEXR.File({"compression": compression, "type": OpenEXR.scanlineimage}, part) as f:
                f.write(f"{tmp}/g.exr")
            out[group] = Path(f"{tmp}/g.exr").stat().st_size
    return out


def measure_bytes(root: str | Path, frames: int = 8) -> dict:
    """Bytes per frame and channel group of ``frames`` complete frames spread evenly over the store:
    as stored, and each image re-encoded with the compact encoding (in a temporary folder).

    Returns ``{"frames": n, "stored"|"compact": {"groups": {group: bytes}, "files": [bytes per frame]}}``.
    """
    import tempfile

    from .exr import write_image
    store = Store(root)
    keys = [k for k in store.frames() if store.frame_record(k.scene, k.frame) is not None]
    picked = [keys[i] for i in sorted({int(i) for i in np.linspace(0, len(keys) - 1, min(frames, len(keys)))})]
    result = {kind: {"groups": dict.fromkeys(GROUPS, 0), "files": []} for kind in ("stored", "compact")}
    with tempfile.TemporaryDirectory() as tmp:
        for key in picked:
            totals = dict.fromkeys(result, 0)
            for name in store.frame_record(key.scene, key.frame)["images"]:
                path = store.image_path(key.scene, key.frame, name)
                arrays, header = read_image(path)
                meta = {k: v for k, v in header.items() if k not in _IMAGE_KEYS}
                write_image(Path(tmp) / "c.exr", arrays, meta=meta, encoding="compact")
                for kind, file in (("stored", path), ("compact", Path(tmp) / "c.exr")):
                    totals[kind] += file.stat().st_size
                    for group, n in group_bytes(file).items():
                        result[kind]["groups"][group] += n
            for kind, n in totals.items():
                result[kind]["files"].append(n)
    result["frames"] = len(picked)
    return result


# What ``measure_encodings`` compares: the render.encoding choices, and the compact values under the
# other lossless compressions every OpenEXR reads (the alternatives to ZIP).
ENCODING_CHOICES = (("compact", None), ("compact", "ZIPS"), ("compact", "PIZ"), ("compact-zstd", None), ("exact", None))


def measure_encodings(root: str | Path, frames: int = 8, repeat: int = 3) -> dict:
    """Bytes, write and read seconds per frame of each of ``ENCODING_CHOICES``, on ``frames`` complete
    frames spread over the store: every image read, written with each (``write_image``: rounding,
    checksum, compression, fsync'd temporary file and rename) and read back (``read_image``: decoding,
    checksum, derived beauty). Seconds are the median of ``repeat`` runs per image (the machine may
    be shared), summed per frame. ``{"frames": n, label: {"bytes", "write_s", "read_s": [per frame]}}``."""
    import tempfile

    from .exr import STORE_ENCODINGS, write_image
    store = Store(root)
    keys = [k for k in store.frames() if store.frame_record(k.scene, k.frame) is not None]
    picked = [keys[i] for i in sorted({int(i) for i in np.linspace(0, len(keys) - 1, min(frames, len(keys)))})]
    labels = {f"{name} ({compression or STORE_ENCODINGS[name][1]})": (name, compression)
              for name, compression in ENCODING_CHOICES}
    result: dict = {label: {"bytes": [], "write_s": [], "read_s": []} for label in labels}
    with tempfile.TemporaryDirectory() as tmp:
        for key in picked:
            totals = {label: dict.fromkeys(("bytes", "write_s", "read_s"), 0.0) for label in labels}
            for name in store.frame_record(key.scene, key.frame)["images"]:
                arrays, header = read_image(store.image_path(key.scene, key.frame, name))
                meta = {k: v for k, v in header.items() if k not in _IMAGE_KEYS}
                for label, (encoding, compression) in labels.items():
                    out = Path(tmp) / "e.exr"
                    writes, reads = [], []
                    for _ in range(repeat):
                        t0 = time.perf_counter()
                        write_image(out, arrays, meta=meta, encoding=encoding, compression=compression)
                        t1 = time.perf_counter()
                        read_image(out)
                        writes.append(t1 - t0)
                        reads.append(time.perf_counter() - t1)
                    totals[label]["bytes"] += out.stat().st_size
                    totals[label]["write_s"] += float(np.median(writes))
                    totals[label]["read_s"] += float(np.median(reads))
            for label, t in totals.items():
                for k, v in t.items():
                    result[label][k].append(v)
    result["frames"] = len(picked)
    return result


def encodings_table(result: dict) -> str:
    """``measure_encodings``'s result as a markdown table, per frame."""
    from .exr import STORE_ENCODINGS
    n = max(result["frames"], 1)
    lines = [f"{result['frames']} frames; per frame (all its images): MiB, seconds to write and to read back", "",
             "| encoding (compression) | MiB | write s | read s | OpenEXR 2.x, 3.0-3.4 read it |",
             "| --- | ---: | ---: | ---: | --- |"]
    for label, r in result.items():
        if label == "frames":
            continue
        old = "no (OpenEXR >= 3.5)" if "ZSTD" in label else "yes"
        default = " (default)" if label == f"compact ({STORE_ENCODINGS['compact'][1]})" else ""
        lines.append(f"| {label}{default} | {sum(r['bytes']) / n / 2**20:.2f} | {sum(r['write_s']) / n:.3f} | "
                     f"{sum(r['read_s']) / n:.3f} | {old} |")
    return "\n".join(lines)


# Record keys that write_image sets itself (the rest is the caller's meta).
_IMAGE_KEYS = {"format", "version", "buffers", "height", "width", "constants", "checksum", "encoding", "layers"}


def bytes_table(result: dict) -> str:
    """``measure_bytes``'s result as a markdown table in MiB per frame."""
    n = max(result["frames"], 1)

    def mib(v: float) -> str:
        return f"{v / n / 2**20:.2f}"

    lines = [f"{result['frames']} frames; MiB per frame (each group written alone, with its own header and "
             "chunks: the groups add up to a few % more than the files)", "",
             "| channel group | stored | compact |", "| --- | ---: | ---: |"]
    for group in GROUPS:
        lines.append(f"| {group} | {mib(result['stored']['groups'][group])} | {mib(result['compact']['groups'][group])} |")
    s, c = result["stored"]["files"], result["compact"]["files"]
    lines.append(f"| **files (mean)** | **{mib(sum(s))}** | **{mib(sum(c))}** |")
    lines.append(f"| files (largest frame) | {max(s, default=0) / 2**20:.2f} | {max(c, default=0) / 2**20:.2f} |")
    return "\n".join(lines)


def run_verify(root: str, quiet: bool = False, pixels: bool = True, jobs: int = 1) -> int:
    t0 = time.perf_counter()
    report = verify_store(root, pixels=pixels, jobs=jobs)
    if not quiet:
        for line in report.problems:
            print(line)
    print(report.summary(time.perf_counter() - t0, pixels))
    return 1 if report.problems else 0
