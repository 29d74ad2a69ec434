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
from clrefract.tracer import Tracer


class OffReference(HashGridField):
    """A hash grid whose NumPy reference is off its kernels by `off`, as a miscompiling
    driver's kernels would be off the reference."""

    off = 0.0

    def eval(self, pts):
        eta, grad = super().eval(pts)
        return eta + self.off, grad

    def _forward2(self, *args, **kw):
        o, og, oh, tape = super()._forward2(*args, **kw)
        return o + self.off, og, oh, tape


def off_by(off: float, seed: int) -> OffReference:
    f = FIELDS["eight-levels"]
    g = OffReference(f.config, BOX, f.data(), seed=seed)
    g.off = off
    return g


@pytest.fixture(autouse=True)
def fresh_checks(monkeypatch):
    monkeypatch.setattr(device_check, "_passed", weakref.WeakSet())


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_kernels_that_match_their_reference_pass(precision):
    Tracer(off_by(0.0, 0), BOX, precision=precision)
    DevicePasses(off_by(0.0, 0), default_runtime(), precision)


@pytest.mark.parametrize("off", [1e-2, np.nan])
def test_a_tracer_off_its_reference_is_refused_naming_the_driver(off):
    with pytest.raises(ClrefractError, match="eta computed on .*driver .*miscompiles") as e:
        Tracer(off_by(off, 1), BOX, precision="float32")
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
        Tracer(FIELDS["eight-levels"], BOX, precision="float32")
    Tracer(FIELDS["smoothstep"], BOX, precision="float32")
    Tracer(FIELDS["smoothstep"], BOX, precision="float64")  # another build
    assert len(calls) == 3
