"""OpenCL drivers that arrive through pip, made visible to pyopencl's ICD loader.

pip PoCL registers itself inside pyopencl. Intel's CPU runtime (`pip install intel-opencl-rt`,
the `cpu` extra) installs its library under the environment's lib/ with an ICD file that names a
build-machine path and with dependencies (libimf, libsvml, ...) outside the loader's search
path. So before the first platform query clrefract loads those dependencies and points the ICD
loader at a folder holding the system's ICD files plus one naming Intel's library. This runs
only where that library is installed and OCL_ICD_VENDORS is not a single file; set
CLREFRACT_NO_PIP_DRIVERS=1 to skip it.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import sys
from pathlib import Path

from .locations import cache_dir

_DONE = False
INTEL_LIB = "libintelocl.so"
INTEL_DEPS = ("libintlc.so.5", "libirng.so", "libimf.so", "libsvml.so")


def _intel_library() -> Path | None:
    for prefix in dict.fromkeys([sys.prefix, sys.base_prefix]):
        lib = Path(prefix) / "lib" / INTEL_LIB
        if lib.is_file():
            return lib
    return None


def register_pip_drivers() -> None:
    """Make pip-installed drivers visible; call before pyopencl lists platforms."""
    global _DONE
    if _DONE or os.environ.get("CLREFRACT_NO_PIP_DRIVERS"):
        return
    _DONE = True
    lib = _intel_library()
    if lib is None or not sys.platform.startswith("linux"):
        return
    src = Path(os.environ.get("OCL_ICD_VENDORS", "/etc/OpenCL/vendors"))
    if src.exists() and not src.is_dir():
        return  # the user named one ICD on purpose
    try:
        for dep in INTEL_DEPS:
            path = lib.parent / dep
            if path.exists():
                ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    except OSError:
        return  # a broken install: leave the loader as it was
    tag = hashlib.sha1(f"{src}|{lib}".encode()).hexdigest()[:12]
    vendors = cache_dir() / "icd" / tag
    try:
        vendors.mkdir(parents=True, exist_ok=True)
        wanted = {"clrefract-intel-cpu.icd": f"{lib}\n"}
        if src.is_dir():
            for icd in sorted(src.glob("*.icd")):
                wanted[icd.name] = icd.read_text()
        for old in vendors.glob("*.icd"):
            if old.name not in wanted:
                old.unlink()
        for name, text in wanted.items():
            path = vendors / name
            if not path.exists() or path.read_text() != text:
                path.write_text(text)
    except OSError:
        return
    os.environ["OCL_ICD_VENDORS"] = str(vendors)
