"""The hash grid's distillation on the device (kernels_cl/hashgrid_distil.cl) against its
float64 NumPy passes: the same o, grad o and parameter gradient, and the same fit."""

import numpy as np
import pytest
from test_field_hashgrid import BOX, FIELDS, SMALL, inner_points, sample_points

import clrefract.fields.hashgrid_passes as passes
from clrefract.errors import ClrefractError
from clrefract.fields.hashgrid import HashGridConfig, HashGridField
from clrefract.fields.hashgrid_passes import DevicePasses, HostPasses
from clrefract.fit import load_config
from clrefract.runtime import default_runtime


def residuals(n, seed=5):
    rng = np.random.default_rng(seed)
    return rng.normal(size=n), rng.normal(size=n), rng.normal(size=(n, 3))


def both_passes(field, precision, lanes, pts, res):
    p = field.data()
    with HostPasses(field, len(pts)) as host:
        ref = (*host.forward(p, pts), host.reverse(*res))
    with DevicePasses(field, default_runtime(), precision, lanes) as dev:
        got = (*dev.forward(p, pts), dev.reverse(*res))
    return ref, got


@pytest.mark.parametrize("name", ["smoothstep", "trilinear", "ramp", "one-layer", "eight-levels"])
@pytest.mark.parametrize("lanes", [1, 16])
def test_device_passes_match_the_numpy_reference_in_float64(name, lanes, monkeypatch):
    """Points inside, in the window's ramp and outside the box (clamped), a count that is
    not a multiple of the lanes, and work-items of the reverse pass that take several
    vectors of points each (the last one fewer)."""
    monkeypatch.setattr(passes, "REVERSE_ITEMS_MAX", 7)
    pts = sample_points(501)
    (o, og, g), (o1, og1, g1) = both_passes(
        FIELDS[name], "float64", lanes, pts, residuals(len(pts))
    )
    n_tab = FIELDS[name].config.n_table_params
    assert np.abs(g[:n_tab]).max() > 0 and np.abs(g[n_tab:]).max() > 0
    assert np.abs(o1 - o).max() < 1e-12 * np.abs(o).max()
    assert np.abs(og1 - og).max() < 1e-12 * np.abs(og).max()
    assert np.abs(g1 - g).max() < 1e-12 * np.abs(g).max()


def test_one_lane_on_a_cpu_runs_in_small_work_groups():
    """8,192 points at one lane: PoCL's own choice of work-group put thousands of copies of
    the encoding's arrays on one thread's stack and crashed the process (a GPU's layout on
    a CPU); tracer.work_group_size keeps groups at 32 there whatever the lanes."""
    field = HashGridField(
        HashGridConfig(levels=8, log2_table=16, n_min=8, n_max=64, hidden=32), BOX
    )
    pts = inner_points(8192, seed=4)
    (o, og, g), (o1, og1, g1) = both_passes(field, "float64", 1, pts, residuals(8192))
    assert np.abs(o1 - o).max() < 1e-12 * np.abs(o).max()
    assert np.abs(g1 - g).max() < 1e-12 * np.abs(g).max()


def test_device_passes_in_float32_round_the_reference():
    pts = inner_points(997, seed=3).astype(np.float32).astype(np.float64)
    (o, og, g), (o1, og1, g1) = both_passes(FIELDS["ramp"], "float32", 16, pts, residuals(997))
    assert np.abs(o1 - o).max() < 1e-5 * np.abs(o).max()
    assert np.abs(og1 - og).max() < 1e-4 * np.abs(og).max()
    assert np.abs(g1 - g).max() < 1e-4 * np.abs(g).max()


def sphere_fit(device):
    pts = inner_points(3000)
    r = np.linalg.norm(pts - pts.mean(0), axis=1)
    eta = 1 + 0.5 / (1 + np.exp(r - 20))
    f = HashGridField(HashGridConfig(**SMALL), BOX, seed=0)
    rms = f.fit_values(pts, eta, iterations=20, batch=700, device=device)
    return f.data(), rms


def test_a_distillation_on_the_device_takes_the_host_steps():
    """The same batches and Adam steps: float64 parameters agree to rounding, float32 ones
    fit as well."""
    host, rms = sphere_fit(None)
    moved = np.abs(host - HashGridField(HashGridConfig(**SMALL), BOX, seed=0).data())
    assert moved.max() > 1e-3
    dev64, rms64 = sphere_fit((default_runtime(), "float64"))
    assert np.abs(dev64 - host).max() < 1e-9 * moved.max()
    assert rms64 == pytest.approx(rms, rel=1e-9)
    _, rms32 = sphere_fit((default_runtime(), "float32"))
    assert rms32 == pytest.approx(rms, rel=1e-2)


def test_distil_on_names_its_choices():
    assert load_config(None, {"field": "hashgrid"}).distil_on == "device"
    with pytest.raises(ClrefractError, match="distil_on must be 'device' or 'host'"):
        load_config(None, {"field": "hashgrid", "distil_on": "gpu"})
