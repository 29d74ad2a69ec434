"""Sizes checked before anything is allocated or launched.

A request that cannot fit is refused in one line that says what was asked and how much
memory it would need, instead of a NumPy MemoryError, an OpenCL allocation failure or an
int32 overflow deep inside a kernel launch.
"""

from __future__ import annotations

import math
import os

from .errors import ClrefractError

INT32_MAX = 2**31 - 1
# bytes of host memory per pixel or ray, measured roughly: origins, directions and radiance in
# float64 plus the temporaries of Camera.rays and of the concatenations
RENDER_BYTES_PER_PIXEL = 200
FIT_BYTES_PER_RAY = 240
# a fit keeps parameters, gradient, two Adam moments, the best parameters and the free mask
FIT_COPIES_PER_PARAM = 8


def fmt_bytes(n: float) -> str:
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} bytes"


def host_memory_bytes() -> int:
    """Physical memory of this machine (64 GiB where the system does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 64 * 2**30


def host_cores() -> int:
    """CPU cores this process may run on (its affinity where the system has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def host_threads() -> int:
    """Threads the host's NumPy work may use: CLREFRACT_HOST_THREADS (MPI ranks that share a
    machine split its cores; clrefract.parallel), else host_cores()."""
    told = os.environ.get("CLREFRACT_HOST_THREADS", "").strip()
    if not told:
        return host_cores()
    if not told.isdigit() or int(told) < 1:
        raise ClrefractError(f"CLREFRACT_HOST_THREADS must be a whole number >= 1, got {told!r}")
    return int(told)


def check_memory(what: str, nbytes: float, available: int | None = None, place="memory") -> None:
    """Refuse `what` when it would need more than the machine (or device) has."""
    available = host_memory_bytes() if available is None else available
    if not nbytes <= available:
        raise ClrefractError(
            f"{what} would need {fmt_bytes(nbytes)} of {place}, more than the "
            f"{fmt_bytes(available)} there is"
        )


def check_count(what: str, value, lo: int = 1, hi: int = INT32_MAX) -> int:
    """A whole number in [lo, hi]: counts that reach OpenCL as int32."""
    if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value):
        raise ClrefractError(f"{what} must be a whole number, got {value!r}")
    if not lo <= value <= hi:
        raise ClrefractError(f"{what} must be between {lo} and {hi}, got {value}")
    return int(value)


def check_image_size(what: str, width: int, height: int, views: int = 1) -> None:
    """Views of width x height pixels, each traced as one launch of that many rays."""
    pixels = int(width) * int(height)
    check_memory(f"{what}: a {width}x{height} view", pixels * RENDER_BYTES_PER_PIXEL)
    if pixels > INT32_MAX:
        raise ClrefractError(
            f"{what}: a {width}x{height} view has {pixels} pixels, more than the "
            f"{INT32_MAX} rays one launch can trace"
        )
    if views < 1:
        raise ClrefractError(f"{what}: need at least one view, got {views}")


def check_training_rays(what: str, rays: int) -> None:
    """Every training pixel is held in memory as a ray with its target for a whole fit."""
    check_memory(f"{what}: {rays} training pixels", rays * FIT_BYTES_PER_RAY)


def max_steps_for(step: float, diagonal: float) -> int:
    """The default step cap (4 box diagonals) of a step, refused where int32 cannot hold it."""
    if not (isinstance(step, int | float) and math.isfinite(step) and step > 0):
        raise ClrefractError(f"step must be a positive number of mm, got {step!r}")
    steps = math.ceil(4 * diagonal / step)
    if steps > INT32_MAX:
        shortest = 4 * diagonal / INT32_MAX
        raise ClrefractError(
            f"step {step:g} mm: a ray across the {diagonal:.0f} mm box would take {steps:.3g} "
            f"steps, more than a step count holds; use a step of at least {shortest:.2g} mm"
        )
    return steps


def check_grid(what: str, res: int, copies: int = FIT_COPIES_PER_PARAM) -> None:
    """A res^3 grid of float64 values, held `copies` times."""
    check_count(what, res, 2, 65536)
    check_memory(f"{what} {res}: a {res}^3 grid", float(res) ** 3 * 8 * copies)


def check_table(levels: int, log2_table: int, features: int) -> None:
    """Hash tables of 2^log2_table entries per level."""
    check_count("log2_table", log2_table, 1, 26)
    check_count("levels", levels, 1, 64)
    entries = float(levels) * 2**log2_table * features
    check_memory(
        f"hash grid of {levels} levels of 2^{log2_table} entries",
        entries * 8 * FIT_COPIES_PER_PARAM,
    )


def check_device_buffer(what: str, nbytes: float, info) -> None:
    """One OpenCL buffer on a device whose RuntimeInfo-like `info` has global_mem_bytes."""
    total = int(getattr(info, "global_mem_bytes", 0) or 0)
    if total:
        check_memory(what, nbytes, total, place=f"device memory on {info.name}")
