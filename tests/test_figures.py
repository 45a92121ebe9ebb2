"""The contact sheet both contact-sheet tools draw (pipeline.figures.contact_sheet), on tiny images: the
self-exposed tonemap, the PNG written via a temporary name, and the timing summary of the random-scene sheet."""
import numpy as np
import pytest
from PIL import Image

from mcdenoise.pipeline.figures import MID_GREY, contact_sheet, exposed
from mcdenoise.pipeline.metrics import linear_to_srgb, reinhard
from tools.contact_sheet import kind_summary


def test_exposed_puts_the_log_average_at_mid_grey_whatever_the_brightness():
    grey = linear_to_srgb(reinhard(MID_GREY))
    for level in (0.1, 1.0, 500.0):     # (1e-4 is added to the luminance before the log: dark images stay dark)
        np.testing.assert_allclose(exposed(np.full((3, 4, 3), level)), grey, rtol=1e-3)
    ramp = np.linspace(0, 8, 4 * 5 * 3).reshape(4, 5, 3)
    shown = exposed(ramp)
    assert shown.shape == ramp.shape and 0 <= shown.min() and shown.max() < 1
    assert np.all(np.diff(shown.ravel()) >= 0)            # a brighter pixel stays brighter
    assert np.all(exposed(np.zeros((2, 2, 3))) == 0)       # black stays black


@pytest.mark.parametrize("exposure", [False, True])
def test_contact_sheet_writes_one_png_and_nothing_else(tmp_path, exposure):
    rng = np.random.default_rng(0)
    cells = [(f"tile {k}", rng.uniform(0, 4, size=(6, 8, 3))) for k in range(3)]
    out = tmp_path / "sheet.png"
    contact_sheet(cells, out, cols=2, title="three tiles", exposure=exposure, cell=1.0)
    assert [p.name for p in tmp_path.iterdir()] == ["sheet.png"]
    with Image.open(out) as im:
        assert im.format == "PNG" and im.size == (2 * 90, 2 * 108)    # 2 x 2 cells of 1 x 1.2 inches at 90 dpi
    with pytest.raises(ValueError, match="sheet.png: a contact sheet needs at least one image"):
        contact_sheet([], out)


def test_the_random_scene_sheets_timings_leave_the_first_frame_out():
    assert kind_summary([[1.0, 5.0], [0.2, 1.0], [0.4, 2.0]]) == {
        "frames": 3, "build_s": 0.3, "render_s": 1.5, "first_frame_s": 6.0}
    assert kind_summary([[1.0, 5.0]]) == {"frames": 1, "build_s": None, "render_s": None, "first_frame_s": 6.0}
    assert kind_summary([]) == {"frames": 0, "build_s": None, "render_s": None, "first_frame_s": None}
