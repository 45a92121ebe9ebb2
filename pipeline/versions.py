"""Package versions and the machine, recorded in manifests, reports and model cards, so a result says
what made it."""
from __future__ import annotations

import os
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


def machine() -> dict:
    """Host, OS, processor, CPU count; with torch installed also its threads and the CUDA device."""
    info = {"host": platform.node(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(), "cpus": os.cpu_count()}
    try:
        import torch
        info["torch_threads"] = torch.get_num_threads()
        info["cuda"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    except ImportError:
        pass
    return info
