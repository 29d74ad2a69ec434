"""Steps that land on analytic fields' kinks keep RK4 / RKN4 fourth order (issue 12)."""

import numpy as np
import pytest

from clrefract.convergence import loglog_slope, luneburg_exit_errors
from clrefract.fields.analytic import Sphere
from clrefract.snell import snell_numpy
from clrefract.tracer import Tracer


@pytest.mark.parametrize("integrator", ["rkn4", "rk4"])
def test_luneburg_exit_direction_is_fourth_order(integrator):
    steps = [1.0, 0.5, 0.25, 0.125]
    r = luneburg_exit_errors(steps, integrator)
    slope = loglog_slope(r["step"], r["error"])
    assert slope > 3.6, r
    assert r["error"][-1] < 1e-9, r


def test_without_interface_steps_the_kink_makes_it_first_order():
    steps = [1.0, 0.5, 0.25, 0.125]
    r = luneburg_exit_errors(steps, "rkn4", interface_steps=False)
    assert loglog_slope(r["step"], r["error"]) < 1.5, r
    assert r["error"][-1] > 1e-3, r


def test_interface_steps_bring_a_sphere_closer_to_snell():
    """A smoothed glass sphere: the band edges are kinks of the smoothstep's derivatives."""
    f = Sphere(radius=20.0, eta=1.5, width=1.0)
    rng = np.random.default_rng(0)
    yz = rng.uniform(-17, 17, (64, 2))
    yz = yz[(yz**2).sum(1) < 17**2][:16]
    o = np.column_stack([np.full(len(yz), -120.0), yz])
    d = np.tile([1.0, 0.0, 0.0], (len(yz), 1))
    want = snell_numpy(f, o, d).direction
    err = {}
    for on in (True, False):
        res = Tracer(f, step=0.25, precision="float64", interface_steps=on).trace(o, d)
        assert np.all(np.isfinite(res.direction))
        err[on] = np.linalg.norm(res.direction - want, axis=1).max()
    assert err[True] < err[False], err
