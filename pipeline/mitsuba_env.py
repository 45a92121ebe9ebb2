"""Import Mitsuba safely: point drjit at LLVM >= 16 first, then choose the variant.

drjit's LLVM backend loads ``libLLVM`` at run time. With LLVM 14/15 (Debian's default) the first
render dies with ``LLVM ERROR: Cannot select: fminimum``, a native abort that takes the whole
process with it, so we refuse to continue instead of letting it crash.
"""
from __future__ import annotations

import glob
import os
import re
import shutil
import subprocess

from .errors import MitsubaSetupError

MIN_LLVM = 16
_SEARCH = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-{v}.so",
    "/usr/lib/aarch64-linux-gnu/libLLVM-{v}.so",
    "/usr/lib/llvm-{v}/lib/libLLVM-{v}.so",
    "/usr/lib/llvm-{v}/lib/libLLVM.so",
    "/usr/lib64/libLLVM-{v}.so",
    "/usr/local/opt/llvm@{v}/lib/libLLVM.dylib",
)


def _llvm_version(path: str) -> int | None:
    m = re.search(r"LLVM[-.]?(\d+)", os.path.basename(path)) or re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def find_libllvm() -> str | None:
    """Path of a libLLVM with major version >= 16, newest first, or None."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        return env
    for v in range(30, MIN_LLVM - 1, -1):
        for pattern in _SEARCH:
            for path in glob.glob(pattern.format(v=v)):
                if os.path.exists(path):
                    return path
    return None


def configure_llvm() -> str:
    """Set ``DRJIT_LIBLLVM_PATH`` (before drjit is imported) or raise a clear error."""
    path = find_libllvm()
    if path is None:
        raise MitsubaSetupError(
            f"no libLLVM >= {MIN_LLVM} found. Mitsuba's llvm_* variants crash with LLVM 14/15. "
            "Install it (Debian/Ubuntu: 'apt-get install libllvm19', or run 'make setup' as root) "
            "or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version 16 or newer.")
    version = _llvm_version(path)
    if version is not None and version < MIN_LLVM:
        raise MitsubaSetupError(f"DRJIT_LIBLLVM_PATH={path} is LLVM {version}; Mitsuba needs >= {MIN_LLVM}.")
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path


def gpu_available() -> bool:
    if shutil.which("nvidia-smi") is None:
        return False
    try:
        return subprocess.run(["nvidia-smi", "-L"], capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def resolve_variant(variant: str = "auto") -> str:
    if variant != "auto":
        return variant
    return "cuda_ad_rgb" if gpu_available() else "llvm_ad_rgb"


_IMPORTED: str | None = None


def import_mitsuba(variant: str = "auto", threads: int = 0):
    """Return the ``mitsuba`` module with ``variant`` set; safe to call repeatedly."""
    global _IMPORTED
    variant = resolve_variant(variant)
    if variant.startswith("llvm"):
        configure_llvm()
    import drjit as dr
    import mitsuba as mi

    if _IMPORTED != variant:
        if variant not in mi.variants():
            raise MitsubaSetupError(f"Mitsuba variant {variant!r} is not available (have: {', '.join(mi.variants())})")
        mi.set_variant(variant)
        _IMPORTED = variant
    if threads > 0:
        dr.set_thread_count(threads)
    return mi
