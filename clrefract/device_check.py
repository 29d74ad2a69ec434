"""A field's kernels checked against its NumPy reference once per device and build.

NVIDIA's driver (580, H100) computed a hash grid's encoding of 8 levels wrong (the MLP's
output off by 18%, or not finite) where it computed 4 levels right, and PoCL both: a fit
there went on from a broken start and scored 14 dB where this CPU gives 34. A few points
evaluated both ways when a program is first used turn that into an error naming the driver.
"""

from __future__ import annotations

import weakref

import numpy as np

from .errors import ClrefractError

CHECK_POINTS = 64
# relative to the reference's largest value (at least 1): float32 rounds the kernels'
# answers to about 1e-6 of it, the failures seen were 1e-2 and more
TOLERANCE = {"float32": 1e-4, "float64": 1e-9}
_passed: weakref.WeakSet = weakref.WeakSet()  # built programs (runtime.Kernels) that passed


def check_points(box, n: int = CHECK_POINTS) -> np.ndarray:
    """Fixed points inside the box, clear of its window."""
    lo = np.asarray(box.lo, float) + 2 * box.margin
    hi = np.asarray(box.hi, float) - 2 * box.margin
    return np.random.default_rng(12345).uniform(lo, hi, (n, 3))


def check_once(runtime, program, precision: str, what: str, compute) -> None:
    """Run `compute()` -> (device's values, NumPy's) the first time `program` (runtime.build's,
    which builds each source, defines and precision once) is used, and refuse the device if
    they differ by more than rounding."""
    if program in _passed:
        return
    got, ref = (np.asarray(a, np.float64) for a in compute())
    scale = max(1.0, float(np.abs(ref).max()))
    err = float(np.abs(got - ref).max()) / scale if np.all(np.isfinite(got)) else np.inf
    tol = TOLERANCE[precision]
    if not err <= tol:
        info = runtime.info
        raise ClrefractError(
            f"{what} computed on {info.platform} / {info.name} (driver "
            f"{info.driver_version}) is off its NumPy reference by {err:.2g} at "
            f"{len(ref)} test points, where {precision} rounding allows {tol:.0e}: this "
            "driver miscompiles these kernels. Use another device (`clrefract devices` "
            "lists them; --device P:D)"
        )
    _passed.add(program)
