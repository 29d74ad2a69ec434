"""A field's kernels are checked against its NumPy reference once per device and build, and a
device whose answers are off is refused with a message naming its driver."""

import weakref

import numpy as np
import pytest
from test_field_hashgrid import BOX, FIELDS

from clrefract import device_check
from clrefract.errors import ClrefractError
from clrefract.fields.hashgrid import HashGridField
from clrefract.fields.hashgrid_passes import DevicePasses
from clrefract.runtime import default_runtime
from clrefract.tracer import Tracer, TraceSettings


class OffReference(HashGridField):
    """A hash grid whose NumPy reference is off its kernels by `off`, as a miscompiling
    driver's kernels would be off the reference."""

    off = 0.0

    def eval(self, pts):
        eta, grad = super().eval(pts)
        return eta + self.off, grad

    def forward2(self, *args, **kw):
        o, og, oh, tape = super().forward2(*args, **kw)
        return o + self.off, og, oh, tape


def off_by(off: float, seed: int) -> OffReference:
    f = FIELDS["eight-levels"]
    g = OffReference(f.config, BOX, f.data(), seed=seed)
    g.off = off
    return g


@pytest.fixture(autouse=True)
def fresh_checks(monkeypatch):
    monkeypatch.setattr(device_check, "_passed", weakref.WeakSet())


# measured on PoCL (CPU) at 200 points: eta off NumPy's by 1.3e-7 (float32) and 2e-16;
# grad eta off central differences (h = 1e-4 mm, their own error 1.8e-8) by 2.2e-7 and
# 1.8e-8, of 0.027 at most; the MLP's o off by 8.8e-7 and 3e-16, grad o off central
# differences by 1.9e-6 and 1.5e-7, of 0.21 at most
TOL = {
    "float32": dict(eta=1e-6, grad=2e-6, o=5e-6, grad_o=1.5e-5),
    "float64": dict(eta=1e-12, grad=2e-7, o=1e-12, grad_o=1.5e-6),
}


def _central(fn, pts, h=1e-4):
    return np.stack([(fn(pts + h * e) - fn(pts - h * e)) / (2 * h) for e in np.eye(3)], 1)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_kernels_that_match_their_reference_pass(precision):
    """Both builds pass their check (recorded as passed), and at points the check does not
    use their values agree with the NumPy reference and their gradients with central
    differences of it."""
    from test_field_hashgrid import inner_points

    tol = TOL[precision]
    pts = inner_points(200, seed=7)
    field = off_by(0.0, 0)
    tr = Tracer(field, BOX, TraceSettings(precision=precision))
    assert tr.kernels in device_check._passed and len(device_check._passed) == 1
    eta, grad = tr.eval_field(pts)
    assert np.ptp(eta) > 0.05  # a field that varies over the points
    assert np.abs(eta - field.eval(pts)[0]).max() < tol["eta"]
    assert np.abs(grad - _central(lambda x: field.eval(x)[0], pts)).max() < tol["grad"]
    passes = DevicePasses(off_by(0.0, 0), default_runtime(), precision)
    assert len(device_check._passed) == 2
    p = field.params_vec
    o, grad_o = passes.forward(p, pts)[:2]
    ref = lambda x: field.forward2(x, None, p, False)[0]  # noqa: E731
    assert np.abs(o - ref(pts)).max() < tol["o"]
    assert np.abs(grad_o - _central(ref, pts)).max() < tol["grad_o"]


@pytest.mark.parametrize("off", [1e-2, np.nan])
def test_a_tracer_off_its_reference_is_refused_naming_the_driver(off):
    with pytest.raises(ClrefractError, match="eta computed on .*driver .*miscompiles") as e:
        Tracer(off_by(off, 1), BOX, TraceSettings(precision="float32"))
    assert default_runtime().info.name in str(e.value)


def test_a_distillation_off_its_reference_is_refused():
    with pytest.raises(ClrefractError, match="MLP output .*off its NumPy reference"):
        DevicePasses(off_by(0.05, 2), default_runtime(), "float32")


def test_each_build_is_checked_once(monkeypatch):
    calls = []
    real = device_check.check_once

    def counted(runtime, program, precision, what, compute):
        if program not in device_check._passed:
            calls.append(program)
        real(runtime, program, precision, what, compute)

    monkeypatch.setattr("clrefract.tracer.check_once", counted)
    for _ in range(3):
        Tracer(FIELDS["eight-levels"], BOX, TraceSettings(precision="float32"))
    Tracer(FIELDS["smoothstep"], BOX, TraceSettings(precision="float32"))
    Tracer(FIELDS["smoothstep"], BOX, TraceSettings(precision="float64"))  # another build
    assert len(calls) == 3
