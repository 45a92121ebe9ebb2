"""Writes dome_studio.exr, the radiance of the emitting dome in metal_dome.xml (run from anywhere).

A 32 x 64 latitude-longitude map (rows: v = polar angle / pi, columns: u = azimuth / 2 pi, Mitsuba's
sphere uv): a dim sky gradient plus three bright rectangular softboxes and a thin strip light. It is
mirror-symmetric about the equator, so it looks the same whichever way up Mitsuba reads the rows
(the floor hides the lower half anyway).
"""
from pathlib import Path

import numpy as np

H, W = 32, 64
theta = (np.arange(H) + 0.5) / H * 180.0          # polar angle from the dome's axis, degrees
phi = (np.arange(W) + 0.5) / W * 360.0
th, ph = np.meshgrid(theta, phi, indexing="ij")
elev = 90.0 - np.abs(90.0 - th)                   # elevation above the equator, same on both halves

t = elev / 90.0
img = (np.array([0.55, 0.45, 0.35]) * (1 - t)[..., None] + np.array([0.25, 0.32, 0.45]) * t[..., None])


def box(phi0, dphi, e0, de, radiance):
    d = np.abs((ph - phi0 + 180.0) % 360.0 - 180.0)
    m = (d < dphi / 2) & (np.abs(elev - e0) < de / 2)
    img[m] = radiance


box(40.0, 30.0, 35.0, 22.0, [30.0, 28.0, 25.0])     # key softbox
box(160.0, 45.0, 25.0, 17.0, [6.0, 7.0, 9.0])       # big cool fill
box(270.0, 12.0, 55.0, 12.0, [60.0, 45.0, 30.0])    # small warm rim light
strip = (np.abs(elev - 12.0) < 3.0) & (np.abs((ph - 220.0 + 180.0) % 360.0 - 180.0) < 60.0)
img[strip] = [12.0, 12.0, 12.0]                     # long thin strip light

out = Path(__file__).resolve().parent / "dome_studio.exr"
import mitsuba as mi  # noqa: E402

mi.set_variant("scalar_rgb")
mi.Bitmap(img.astype(np.float16)).write(str(out))
print(out, out.stat().st_size, "bytes")
