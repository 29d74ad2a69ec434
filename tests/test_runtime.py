"""Device choice, program specialisation and the errors users see."""

import dataclasses

import numpy as np
import pytest

from clrefract.errors import ClrefractError
from clrefract.fields.analytic import Sphere
from clrefract.runtime import Runtime, default_runtime, list_devices
from clrefract.tracer import Tracer, TraceSettings


def test_devices_are_listed_with_their_capabilities():
    infos = list_devices()
    assert infos, "the tests need an OpenCL device (PoCL)"
    for i in infos:
        assert i.compute_units >= 1 and i.global_mem_bytes > 0 and i.kind in ("cpu", "gpu", "other")


def test_unknown_device_names_the_choices():
    with pytest.raises(ClrefractError, match="(?s)Unknown OpenCL device .no-such-gpu.*0:0"):
        Runtime("no-such-gpu")
    with pytest.raises(ClrefractError, match="Unknown OpenCL device '7:3'"):
        Runtime("7:3")


def test_device_by_index_and_by_env(monkeypatch):
    first = list_devices()[0]
    assert Runtime(first.selector).info == first
    monkeypatch.setenv("PYOPENCL_CTX", first.selector)
    assert Runtime().info == first


def test_float64_on_a_device_without_it_is_refused():
    rt = Runtime()
    rt.info = dataclasses.replace(rt.info, fp64=False)
    with pytest.raises(ClrefractError, match="float64 was requested.*cl_khr_fp64"):
        Tracer(Sphere(), settings=TraceSettings(precision="float64"), runtime=rt)


@pytest.mark.parametrize("step", [0.0, -1.0, float("nan"), float("inf")])
def test_non_positive_step_is_refused(step):
    with pytest.raises(ClrefractError, match="step must be a positive"):
        Tracer(Sphere(), settings=TraceSettings(step=step))


def test_build_failure_reports_the_compiler_log():
    rt = default_runtime()
    with pytest.raises(ClrefractError, match="no FIELD_\\* kind defined"):
        rt.build(
            ["common.h", "field_analytic.cl", "trace.cl"],
            {"GEO_AT": 0, "INTEGRATOR_RKN4": 1},
            "float32",
        )


def test_programs_are_built_once_and_kernels_reused():
    rt = default_runtime()
    a = Tracer(Sphere(), settings=TraceSettings(step=0.5), runtime=rt)
    # same build, other parameters
    b = Tracer(Sphere(radius=10.0), settings=TraceSettings(step=0.25), runtime=rt)
    assert a.trace_kernel is b.trace_kernel
    c = Tracer(Sphere(), settings=TraceSettings(step=0.5, integrator="euler"), runtime=rt)
    assert c.trace_kernel is not a.trace_kernel


def test_bad_ray_arrays_are_refused():
    tr = Tracer(Sphere())
    with pytest.raises(ClrefractError, match="shape"):
        tr.trace(np.zeros((4, 2)), np.ones((4, 2)))
    with pytest.raises(ClrefractError, match="non-finite"):
        tr.trace(np.full((1, 3), np.nan), np.ones((1, 3)))
    with pytest.raises(ClrefractError, match="zero vector"):
        tr.trace(np.zeros((1, 3)), np.zeros((1, 3)))
