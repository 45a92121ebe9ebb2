"""The ``denoise`` and ``pack`` commands of ``python -m pipeline``.

    denoise (--frame SCENE/FRAME | --exr FILE)  → cmd_denoise(...)         an EXR with the denoised colour
                                                  cmd_denoise_oidn(...)    the same with OIDN itself
    pack                                        → cmd_pack(cfg, splits)    <runs>/pack/<split>_oidn_base*.safetensors
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from mcdenoise.pipeline.config import Config
from mcdenoise.pipeline.ensemble import ensemble as ensemble_mean
from mcdenoise.pipeline.errors import TrainError
from mcdenoise.pipeline.exr import StoreError, write_output
from mcdenoise.pipeline.numerics import repair_nonfinite
from mcdenoise.pipeline.store import FrameKey, Store

from .model import find_run

DEFAULT_EXR_SPP = 16


def _exr_spp(path: Path) -> tuple[int, str]:
    """The sample count an EXR's mcdenoise header records, else ``DEFAULT_EXR_SPP`` (the middle of 4..64)."""
    from mcdenoise.pipeline.exr import read_header
    try:
        spp = read_header(path).get("spp")
    except StoreError:
        spp = None
    if isinstance(spp, int) and spp > 0:
        return spp, "from its header"
    return DEFAULT_EXR_SPP, "not recorded in the file: assumed"


def _warn_if_correlated(exr: str, color: np.ndarray) -> None:
    """A warning on stderr when the input's noise is spatially correlated (pipeline/noise.py)."""
    from mcdenoise.pipeline.noise import CORRELATED_BELOW, correlated_noise

    ratio = correlated_noise(color)
    if ratio is not None:
        print(f"warning: {exr}: its noise looks spatially correlated (neighbour ratio {ratio:.2f} < "
              f"{CORRELATED_BELOW}), as a wide reconstruction filter makes it (Mitsuba's default 'gaussian', "
              "'tent'); OIDN, this denoiser's first estimate, leaves such noise in place. Render with "
              "<rfilter type=\"box\"/> in the film (a nearly noise-free image can read this way too).",
              file=sys.stderr, flush=True)


def cmd_denoise(cfg: Config, spp: int, frame: str | None, exr: str | None, out: str, skip: int | None,
                seed: int | None, base_only: bool = False, quiet: bool = False, steps: int | None = None,
                samples: int | None = None, ensemble: int = 1, strength: float | None = None,
                device: str | None = None, precision: str = "auto") -> int:
    """Denoise one frame of the store (``SCENE/FRAME``) or one EXR and write ``out`` (EXR: ``color``, the
    mean of ``samples`` samples, and ``std``, their per-pixel standard deviation); ``ensemble``: the mean of
    both over that many flipped and transposed copies (``pipeline.ensemble``); ``strength``: the fraction of
    the Control Module's change applied (default: the model's)."""
    from .infer import load_denoiser

    if (frame is None) == (exr is None):
        raise TrainError("give exactly one of --frame SCENE/FRAME or --exr FILE")
    if frame is not None and spp is None:
        raise TrainError("--frame needs --spp (which of the store's sample counts to denoise)")
    if exr is not None and spp is None:
        spp, how = _exr_spp(Path(exr))
        if not quiet:
            print(f"{exr}: {spp} spp ({how}; pass --spp to say otherwise)", flush=True)
    f = cfg.diffusion
    den = load_denoiser(find_run(cfg, spp), device or f.device, base_only, precision)
    buffers, source = _read_input(cfg, frame, exr, spp)
    samples = f.samples if samples is None else int(samples)
    if samples < 1:
        raise TrainError(f"--samples {samples}: expected at least 1")
    def run(b):   # colour and std side by side, so that one self-ensemble turns both back
        return np.concatenate(den.denoise(b, int(spp), skip=skip, seed=cfg.seed if seed is None else seed,
                                          steps=steps, samples=samples, with_std=True, strength=strength), axis=2)
    t0 = time.perf_counter()
    out6 = ensemble_mean(run, buffers, ensemble)
    hdr, std, seconds = out6[..., :3], out6[..., 3:], time.perf_counter() - t0
    meta = {"image": "denoised", "source": source, "spp": int(spp), "method": den.name,
            "skip": den.formulation.skip if skip is None else skip, "steps": steps, "samples": samples,
            "formulation": den.formulation.record(), "repaired_nonfinite": den.last_repaired,
            "clamped_pixels": den.last_clamped, "black_input": den.last_black,
            "estimate_only": den.last_estimate_only, "fallback": getattr(den, "fallback", ""),
            "base_only": getattr(den, "last_base_only", False), "shortened_normals": getattr(den, "last_shortened", 0),
            "ensemble": ensemble, "strength": getattr(den, "strength", 1.0) if strength is None else strength,
            "seconds": round(seconds, 3)}
    write_output(Path(out), hdr, meta, layers={"std": std})
    if not quiet:
        fallback = getattr(den, "fallback", "")
        alone = (f"; no albedo/normal layers: {fallback} on the colour{' and albedo' if 'albedo' in buffers else ''}"
                 if fallback else "; no variance/albedo/normal layers: the first estimate (OIDN) alone")
        print(f"denoised {source} ({hdr.shape[1]}x{hdr.shape[0]}, {spp} spp, {den.name}"
              f"{f', self-ensemble of {ensemble}' if ensemble > 1 else ''}) in {seconds:.1f} s"
              f" -> {out}" + (f"; {den.last_repaired} non-finite input values replaced by 0" if den.last_repaired
                              else "") + (alone if den.last_estimate_only else "")
              + ("; colour, albedo and normal only: the model's base alone (its model.json: control_without_groups)"
                 if getattr(den, "last_base_only", False) else ""), flush=True)
    return 0



def oidn_weights_for(cfg: Config, network: str) -> tuple[bytes, str]:
    """(the TZA blob, where it came from) that ``denoise --method oidn_ft`` runs for ``network``: the
    config's oidn_ft run of that network."""
    from mcdenoise.pipeline.runs import run_dir as model_dir

    from .oidn_ft import export_blob, load_run
    folder = model_dir(cfg, "oidn_ft", variant=network)
    if (folder / "model.safetensors").exists():
        return export_blob(load_run(folder, cfg)[0]), str(folder)
    raise TrainError(f"no oidn_ft run for OIDN's {network} network in {folder}: train it with "
                     f"`make train MODEL=oidn_ft SPP=any oidn_ft.network={network}`, or give --oidn-weights FILE.tza")


def _card_network(weights_file: str) -> str:
    """The network named by the card ``export --format oidn`` writes beside a .tza (``<file>.json``); ''."""
    card = Path(weights_file).with_suffix(".json")
    try:
        return str(json.loads(card.read_text()).get("network", "")) if card.is_file() else ""
    except (OSError, ValueError):
        return ""


def cmd_denoise_oidn(cfg: Config, frame: str | None, exr: str | None, out: str, method: str,
                     weights_file: str | None, spp: int | None = None, quiet: bool = False, ensemble: int = 1) -> int:
    """Denoise a store frame or an EXR with OIDN itself: its built-in network (``oidn``), its final-frame
    mode with the aux prefiltered (``oidn_prefilter``, on albedo and normal), an oidn_ft run (``oidn_ft``)
    or the weights of ``weights_file``, on the layers the input has (colour; +albedo; +albedo+normal), at
    OIDN's speed. ``oidn_ft_prefilter``, and a ``weights_file`` whose card names a ``_calb_cnrm`` network,
    run in the final-frame mode."""
    from mcdenoise.pipeline import oidn, oidn_weights as ow, tza
    from mcdenoise.pipeline.oidn_net import UNet

    if (frame is None) == (exr is None):
        raise TrainError("give exactly one of --frame SCENE/FRAME or --exr FILE")
    buffers, source = _read_input(cfg, frame, exr, spp)
    # OIDN spreads a NaN/Inf over its receptive field: lost samples count as 0, as in every denoiser here
    buffers = {k: np.array(v, dtype=np.float32, copy=True) for k, v in buffers.items()}
    repaired = sum(repair_nonfinite(buffers).values())
    layers = [a for a in ("albedo", "normal") if a in buffers]
    layers = layers if layers and layers[0] == "albedo" else []
    network = ow.network_for("albedo" in layers, "normal" in layers)
    clean_aux = (method in ("oidn_prefilter", "oidn_ft_prefilter") and not weights_file
                 or bool(weights_file) and ow.clean_aux(_card_network(weights_file)))
    if clean_aux and len(layers) < 2:
        what = f"--method {method}" if not weights_file else f"{weights_file} (OIDN's final-frame network)"
        raise TrainError(f"{what} prefilters albedo and normal, but {source} has only "
                         f"{', '.join(['colour', *layers])}; use --method oidn")
    blob, origin = None, ("pyoidn built-in rt_hdr_calb_cnrm_large on albedo and normal prefiltered by OIDN"
                          if clean_aux else f"pyoidn built-in {network}")
    if weights_file:
        blob, origin = ow.load(network, weights_file), weights_file
        need = (UNet.from_tza(tza.read(blob, weights_file)).in_channels - 3) // 3
        if need > len(layers):
            raise TrainError(f"{weights_file}: these OIDN weights read {3 + 3 * need} channels (colour"
                             f"{', albedo' if need else ''}{', normal' if need > 1 else ''}), but {source} has only "
                             f"{', '.join(['colour', *layers])}")
        layers = layers[:need]
    elif method == "oidn_ft":
        blob, origin = oidn_weights_for(cfg, network)
    elif method == "oidn_ft_prefilter":
        blob, origin = oidn_weights_for(cfg, "rt_hdr_calb_cnrm_large")
    t = time.perf_counter()
    hdr = ensemble_mean(lambda b: oidn.denoise(b, aux=bool(layers), weights=blob, clean_aux=clean_aux),
                        {"color": buffers["color"], **{a: buffers[a] for a in layers}}, ensemble)
    seconds = time.perf_counter() - t
    meta = {"image": "denoised", "source": source, "method": method, "weights": origin,
            "inputs": ["color", *layers], "ensemble": ensemble, "repaired_nonfinite": repaired,
            "seconds": round(seconds, 3)}
    write_output(Path(out), hdr, meta)
    if not quiet:
        print(f"denoised {source} ({hdr.shape[1]}x{hdr.shape[0]}; {', '.join(['colour', *layers])}) with OIDN "
              f"({origin}) in {seconds:.2f} s -> {out}"
              + (f"; {repaired} non-finite input values replaced by 0" if repaired else ""), flush=True)
    return 0


def _read_input(cfg: Config, frame: str | None, exr: str | None, spp: int | None) -> tuple[dict, str]:
    """The buffers of ``--frame SCENE/FRAME`` (at ``spp``) or ``--exr FILE``, and how to name the source."""
    if exr is not None:
        from mcdenoise.pipeline.exr import read_layers
        aliased: dict = {}
        buffers = read_layers(Path(exr), aliased)
        for name, channels in aliased.items():
            print(f"{exr}: {name} from {channels[0].rsplit('.', 1)[0]!r} ({', '.join(channels)})", flush=True)
        _warn_if_correlated(exr, buffers["color"])
        return buffers, exr
    if spp is None:
        raise TrainError("--frame needs --spp (which of the store's sample counts to denoise)")
    store, key = Store(cfg.store), _frame_key(frame)
    return store.read(key.scene, key.frame, int(spp)), f"{store.root}/{frame}"


def _frame_key(frame: str) -> FrameKey:
    """``--frame SCENE/FRAME`` as a store key."""
    try:
        scene, idx = frame.split("/")
        return FrameKey(scene, int(idx))
    except ValueError:
        raise TrainError(f"--frame {frame!r}: expected SCENE/FRAME, e.g. s00000/000") from None


def cmd_pack(cfg: Config, splits: list[str], quiet: bool = False) -> int:
    """Write the training packs of ``splits`` (``train.data.ensure_pack``) for the configured base's inputs."""
    from .data import StoreSource, ensure_pack

    source = StoreSource(cfg)
    for split in splits:
        keys = source.store.frames_with(split)
        if not keys:
            raise TrainError(f"{source.store.root}: no {split} frame with gt_clean; run `make gt-clean`")
        path = ensure_pack(source.store, keys, source.pack_path(split), quiet, source.clean_aux)
        print(f"pack {split}: {len(keys)} frames -> {path} ({path.stat().st_size / 2**20:.1f} MiB)", flush=True)
    return 0
