"""OIDN's network in PyTorch (train.model), its weights (train.oidn, pipeline.weights)
and OIDN running weights we wrote (train.oidn.denoise(weights=...)), against pyoidn itself."""
import numpy as np
import pytest
import torch

from mcdenoise.pipeline.errors import WeightsError
from mcdenoise.pipeline.weights import TZATensor, read_tza, write_tza
from mcdenoise.train import oidn
from mcdenoise.train.model import (
    HDR_MAX,
    UNET_LARGE,
    UNet,
    autoexposure,
    from_pu,
    load_unet,
    prefilter_aux_twin,
    to_pu,
    unet_denoise,
)
from tests.helpers import cornell_box_aux

SETS = {"rt_hdr": (), "rt_hdr_alb": ("albedo",), "rt_hdr_alb_nrm": ("albedo", "normal")}


def tonemapped_psnr(a: np.ndarray, b: np.ndarray) -> float:
    ta, tb = np.maximum(a, 0) / (1 + np.maximum(a, 0)), np.maximum(b, 0) / (1 + np.maximum(b, 0))
    mse = float(np.mean((ta.astype(np.float64) - tb) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1 / mse)


@pytest.fixture(scope="module")
def frame():
    """A real 4 spp render of an odd size (61x45: padded to 64x48 inside the network)."""
    torch.set_num_threads(1)
    return cornell_box_aux(61, 45, spp=4)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SETS))
@pytest.mark.parametrize("gain", [1.0, 1e-3])
def test_twin_equals_pyoidn(frame, name, gain):
    """Colour, +albedo, +albedo+normal; at the render's exposure and 1000x darker (autoexposure ~1e3)."""
    buffers = {**frame, "color": frame["color"] * gain}
    aux = [buffers[k] for k in SETS[name]]
    if gain != 1.0:
        assert autoexposure(buffers["color"]) > 100 * autoexposure(frame["color"])
    ours = unet_denoise(load_unet(name), buffers["color"], *aux)
    stock = oidn.denoise({"color": buffers["color"], **dict(zip(SETS[name], aux))}, aux=bool(aux))
    assert ours.shape == stock.shape == frame["color"].shape
    assert tonemapped_psnr(ours / gain, stock / gain) >= 100
    # ... and the network is not the identity: it changes the noisy input a lot
    assert tonemapped_psnr(stock / gain, frame["color"]) < 40


def test_every_builtin_blob_round_trips_bit_exactly():
    table = oidn.blobs(str(oidn.library_path()))
    assert {"rt_hdr", "rt_hdr_alb", "rt_hdr_alb_nrm", "rt_hdr_small"} <= set(table)
    for name in table:
        blob = oidn.weights_blob(name)
        assert write_tza(read_tza(blob, name)) == blob, name


def test_unet_shapes_come_from_the_blob():
    for name, channels in (("rt_hdr", 3), ("rt_hdr_alb", 6), ("rt_hdr_alb_nrm", 9), ("rt_hdr_alb_nrm_small", 9)):
        net = load_unet(name)
        assert net.in_channels == channels
        assert net.widths["dec_conv1a"][1] == net.widths["dec_conv2b"][0] + channels
    full = load_unet("rt_hdr_alb_nrm")
    assert sum(p.numel() for p in full.parameters()) == 919_811
    assert sum(p.numel() for p in load_unet("rt_hdr_alb_nrm_small").parameters()) < 400_000
    # weights written back are the file's float16 values exactly
    back = full.to_tza()
    blob = read_tza(oidn.weights_blob("rt_hdr_alb_nrm"))
    assert all(np.array_equal(back[k].array, blob[k].array) and back[k].layout == blob[k].layout for k in blob)


@pytest.mark.slow
def test_oidn_runs_weights_we_wrote(frame):
    net = load_unet("rt_hdr_alb_nrm")
    same = write_tza(net.to_tza())
    stock = oidn.denoise(frame)
    np.testing.assert_array_equal(oidn.denoise(frame, weights=same), stock)
    with torch.no_grad():
        net.dec_conv0.bias += torch.tensor([0.02, -0.01, 0.01])
        net.enc_conv2.weight.mul_(1.05)
    changed = write_tza(net.to_tza())
    theirs = oidn.denoise(frame, weights=changed)
    ours = unet_denoise(UNet.from_tza(read_tza(changed)), frame["color"], frame["albedo"],
                            frame["normal"])
    assert tonemapped_psnr(theirs, ours) >= 80
    assert tonemapped_psnr(theirs, stock) < 50
    # the stock filter is untouched by the custom one
    np.testing.assert_array_equal(oidn.denoise(frame), stock)


@pytest.mark.slow
def test_oidn_refuses_bad_blobs(frame):
    net = load_unet("rt_hdr_alb_nrm")
    as_float32 = {k: TZATensor(v.array.astype(np.float32), v.layout) for k, v in net.to_tza().items()}
    with pytest.raises(WeightsError, match="OIDN refused"):
        oidn.denoise(frame, weights=write_tza(as_float32))
    with pytest.raises(WeightsError, match="OIDN refused"):
        oidn.denoise(frame, weights=b"\x00" * 4096)
    with pytest.raises(WeightsError, match="OIDN refused"):   # colour-only weights for 9 input channels
        oidn.denoise(frame, weights=oidn.weights_blob("rt_hdr"))


def test_the_aux_prefilter_denoises_albedo_and_normal():
    """OIDN's aux networks (an RT filter given only albedo or only normal) remove noise from them and
    keep them in range."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:64, 0:80] / 80.0
    albedo = np.stack([0.2 + 0.6 * x, 0.5 + 0.0 * x, 0.8 - 0.5 * y], -1).astype(np.float32)
    normal = np.stack([np.sin(x), np.cos(x), 0.3 + 0.0 * y], -1).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    noisy_a = np.clip(albedo + rng.normal(0, 0.08, albedo.shape), 0, 1).astype(np.float32)
    noisy_n = np.clip(normal + rng.normal(0, 0.15, normal.shape), -1, 1).astype(np.float32)
    clean_a, clean_n = oidn.prefilter_aux(noisy_a, noisy_n)
    assert clean_a.dtype == clean_n.dtype == np.float32 and clean_a.shape == clean_n.shape == albedo.shape
    assert clean_a.min() >= 0 and clean_a.max() <= 1 and np.abs(clean_n).max() <= 1
    for noisy, out, truth in ((noisy_a, clean_a, albedo), (noisy_n, clean_n, normal)):
        assert np.mean((out - truth) ** 2) < 0.25 * np.mean((noisy - truth) ** 2)


def test_the_pytorch_aux_prefilter_equals_oidns(frame):
    """OIDN's aux networks run in PyTorch (``device=``: what a GPU machine without pyoidn runs) give what
    pyoidn's filter gives on a real render's noisy albedo and normal, at an odd size."""
    def db(a, b):
        return 10 * np.log10(1 / float(np.mean((a.astype(np.float64) - b) ** 2)))
    stock = oidn.prefilter_aux(frame["albedo"], frame["normal"])
    twin = prefilter_aux_twin(frame["albedo"], frame["normal"], "cpu")
    for ours, theirs, noisy in zip(twin, stock, (frame["albedo"], frame["normal"])):
        assert ours.shape == theirs.shape == noisy.shape and ours.dtype == np.float32
        assert db(ours, theirs) >= 100
        assert db(theirs, noisy) < 60      # the filter is not the identity


@pytest.mark.slow
def test_clean_aux_mode_is_the_prefilter_then_the_large_clean_aux_network(frame):
    """``clean_aux``: the aux prefiltered, then OIDN's network for noise-free aux (at quality high its
    _large variant, whose blob run as custom weights on the same inputs gives the same output)."""
    import pyoidn
    clean = oidn.denoise(frame, clean_aux=True)
    albedo, normal = oidn.prefilter_aux(np.clip(frame["albedo"], 0, 1), np.clip(frame["normal"], -1, 1))
    by_hand = pyoidn.denoise(frame["color"], albedo, normal, hdr=True, clean_aux=True, quality="high")
    np.testing.assert_array_equal(by_hand, clean)
    large = oidn.weights_blob("rt_hdr_calb_cnrm_large")
    np.testing.assert_array_equal(oidn.denoise(frame, weights=large, clean_aux=True), clean)
    assert tonemapped_psnr(clean, oidn.denoise(frame)) < 60     # another network on other aux
    # without aux there is nothing to prefilter: the colour-only network, as without the flag
    color = {"color": frame["color"]}
    np.testing.assert_array_equal(oidn.denoise(color, clean_aux=True), oidn.denoise(color))
    # ... nor for albedo alone (OIDN has no clean-aux network for it)
    albedo_only = {"color": frame["color"], "albedo": frame["albedo"]}
    np.testing.assert_array_equal(oidn.denoise(albedo_only, clean_aux=True), oidn.denoise(albedo_only))
    # the evaluator's row runs this mode, on colour, albedo and normal only
    from mcdenoise.evaluate.methods import Loader
    from mcdenoise.pipeline.config import load_config
    row = Loader(load_config(None, ["eval.device=cpu"])).load("oidn_prefilter", 4)
    extra = {"depth": np.ones_like(frame["color"][..., :1])}
    np.testing.assert_array_equal(row.denoise({**frame, **extra}), clean)


@pytest.mark.slow
def test_the_large_twin_equals_oidn_on_prefiltered_aux(frame):
    """OIDN's UNetLarge (rt_hdr_calb_cnrm_large, 3.85 M parameters) in PyTorch on the prefiltered aux equals
    OIDN's prefiltered-aux mode, and its weights go back into OIDN unchanged."""
    net = load_unet("rt_hdr_calb_cnrm_large")
    assert net.layout is UNET_LARGE and net.in_channels == 9
    assert sum(p.numel() for p in net.parameters()) == 3_848_387
    albedo, normal = oidn.prefilter_aux(np.clip(frame["albedo"], 0, 1), np.clip(frame["normal"], -1, 1))
    ours = unet_denoise(net, frame["color"], albedo, normal)
    stock = oidn.denoise(frame, clean_aux=True)
    assert tonemapped_psnr(ours, stock) >= 100
    assert write_tza(net.to_tza()) == oidn.weights_blob("rt_hdr_calb_cnrm_large")


def test_pu_transfer_inverts():
    y = torch.cat([torch.zeros(1), torch.logspace(-9, np.log10(HDR_MAX), 2000, dtype=torch.float64)])
    x = to_pu(y)
    assert float(x[0]) == 0 and abs(float(x[-1]) - 1) < 1e-9
    assert bool(torch.all(x[1:] > x[:-1]))          # strictly increasing
    back = from_pu(x)
    assert float(torch.max(torch.abs(back - y) / (y + 1e-12))) < 1e-6


def test_autoexposure():
    # a grey image of luminance L exposes to 0.18 / L
    assert autoexposure(np.full((40, 50, 3), 2.0, np.float32)) == pytest.approx(0.09, rel=1e-6)
    # black, NaN and negative values count as 0: nothing above 1e-8 -> 1
    assert autoexposure(np.zeros((8, 8, 3), np.float32)) == 1.0
    bad = np.full((8, 8, 3), np.nan, np.float32)
    bad[:4] = -1
    assert autoexposure(bad) == 1.0
    # bins (16x16 here) average before the log: half black, half 1 -> per bin mean 0.5 (2 bins of 16x16 each)
    img = np.zeros((16, 32, 3), np.float32)
    img[::2, :16] = 1.0
    img[:, 16:] = 0.5
    assert autoexposure(img) == pytest.approx(0.36, rel=1e-6)


def test_missing_weights_say_where_and_what_to_do(tmp_path, monkeypatch):
    with pytest.raises(WeightsError, match=r"nope\.tza: cannot read OIDN weights"):
        oidn.weights_blob("rt_hdr", tmp_path / "nope.tza")
    with pytest.raises(WeightsError, match=r"no weights named 'rt_unknown' \(it has .*rt_hdr_alb_nrm"):
        oidn.weights_blob("rt_unknown")
    (tmp_path / "bad.tza").write_bytes(b"not a tza file at all")
    with pytest.raises(WeightsError, match=r"bad\.tza: not a TZA archive"):
        load_unet("rt_hdr", tmp_path / "bad.tza")
    import importlib.util
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(WeightsError, match="pyoidn is not installed.*oidn.weights=FILE.tza") as info:
        oidn.weights_blob("rt_hdr")
    assert "\n" not in str(info.value)


def test_a_tza_file_loads_like_the_builtin(tmp_path):
    path = tmp_path / "mine.tza"
    path.write_bytes(oidn.weights_blob("rt_hdr_alb"))
    a, b = load_unet("rt_hdr_alb", path), load_unet("rt_hdr_alb")
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))


def test_tza_reader_rejects_damage():
    blob = bytearray(oidn.weights_blob("rt_hdr_small"))
    with pytest.raises(WeightsError, match="version"):
        read_tza(bytes(blob[:2]) + bytes([3]) + bytes(blob[3:]))
    with pytest.raises(WeightsError, match="table at byte .* outside the blob"):
        read_tza(bytes(blob[: len(blob) // 2]) + bytes(blob[-200:]))
    with pytest.raises(WeightsError, match="layout"):
        write_tza({"w": TZATensor(np.zeros((2, 2), np.float16), "x")})
