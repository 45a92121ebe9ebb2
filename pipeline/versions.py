"""Package versions recorded in every manifest, so a dataset says what made it."""
from __future__ import annotations

import platform
from importlib import metadata

PACKAGES = ("mitsuba", "drjit", "numpy", "OpenEXR", "trimesh", "torch", "PyYAML")


def package_versions(extra: tuple[str, ...] = ()) -> dict[str, str]:
    """Versions of ``PACKAGES`` (and of the ``extra`` distributions a stage also uses)."""
    out = {"python": platform.python_version()}
    for name in PACKAGES + tuple(extra):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out
