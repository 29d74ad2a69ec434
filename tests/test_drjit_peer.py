"""tools/drjit_peer.py's hash grid (the bench's Dr.Jit row) is clrefract's: the same eta and
grad eta as the NumPy reference, the same rays as the float64 tracer. Needs the `bench` extra."""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("drjit")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))

from bench_trace import BOX, hashgrid_export, workload  # noqa: E402
from drjit_peer import drjit_eval_hashgrid, drjit_trace_hashgrid  # noqa: E402

from clrefract.fields.hashgrid import HashGridConfig, HashGridField  # noqa: E402
from clrefract.tracer import Tracer, TraceSettings  # noqa: E402

# a dense and two hashed levels, tables large enough to bend rays
CFG = HashGridConfig(levels=3, log2_table=10, n_min=4, n_max=32, hidden=8, eta_max=1.5)


def _field(output):
    f = HashGridField(replace(CFG, output=output), BOX, seed=1)
    p = f.data().copy()
    p[f.table_slice] = np.random.default_rng(2).uniform(-1, 1, CFG.n_table_params)
    p[-1] = 0.3  # the output's bias: eta well inside its range
    f.set_data(p)
    return f


@pytest.mark.parametrize("output", ["sigmoid", "ramp"])
def test_peer_field_is_the_reference(output):
    """Measured 2e-16 (eta) and 7e-16 (grad eta) in float64, 5e-7 in float32."""
    f = _field(output)
    pts = np.random.default_rng(0).uniform(-52, 52, (3000, 3))
    eta_ref, grad_ref = f.eval(pts)
    assert np.ptp(eta_ref) > 0.03 and np.abs(grad_ref).max() > 0.01  # a varied field
    eta, grad = drjit_eval_hashgrid(pts, hashgrid_export(f), "float64")
    assert np.abs(eta - eta_ref).max() < 1e-13 and np.abs(grad - grad_ref).max() < 1e-13


def test_peer_traces_the_rays_the_float64_tracer_does():
    """Exit directions to 1e-14 (measured); the peer counts the step that leaves the box,
    clrefract does not: one more per exiting ray."""
    f = _field("sigmoid")
    o, d = workload(256)
    ref = Tracer(f, BOX, TraceSettings(step=0.5, precision="float64", lanes=8)).trace(o, d)
    res = drjit_trace_hashgrid(o, d, hashgrid_export(f), BOX.lo, BOX.hi, 0.5, 2088, "float64")
    assert np.array_equal(res["status"], ref.status)
    assert np.abs(res["direction"] - ref.direction).max() < 1e-12
    assert np.abs(ref.direction - d).max() > 1e-3  # the field bends them
    assert np.array_equal(res["steps"], ref.steps + (ref.status == 0))
