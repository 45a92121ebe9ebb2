"""The rounding of the numbers of a scene description (``render.scene`` and the generators it calls):
4 decimals, the camera's poses 5. The seeded scenes are drawn through it (later draws and checks read the
rounded values), so the same seed gives the same description only while it stays as it is."""
from __future__ import annotations


def rnd(x: float, nd: int = 4) -> float:
    return round(float(x), nd)


def vec(v, nd: int = 4) -> list:
    return [rnd(x, nd) for x in v]
