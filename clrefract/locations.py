"""Where clrefract reads its OpenCL sources and keeps its cache: what the runtime, the lane
probe and the pip-driver set-up share, so it sits below all three."""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

from .errors import ClrefractError


def cache_dir() -> Path:
    """CLREFRACT_CACHE_DIR, else $XDG_CACHE_HOME/clrefract, else ~/.cache/clrefract."""
    env = os.environ.get("CLREFRACT_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "clrefract"


def kernel_source(name: str) -> str:
    """Text of one OpenCL source shipped in the package (`kernels_cl/` in the repository).

    Code imported from a checkout uses that checkout's kernels_cl/ beside it: an installed
    package (editable ones included) may map clrefract.kernels_cl to another checkout."""
    beside = Path(__file__).resolve().parent.parent / "kernels_cl" / name
    if beside.is_file():
        return beside.read_text()
    try:
        return resources.files("clrefract.kernels_cl").joinpath(name).read_text()
    except (FileNotFoundError, ModuleNotFoundError) as exc:
        raise ClrefractError(f"kernel source {name!r} is missing from the package: {exc}") from None
