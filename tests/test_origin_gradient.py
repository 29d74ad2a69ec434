"""The gradient of the loss with respect to the rays' origins (a camera centre's share, which
a fit of camera centres sums per view), against central differences of the traced loss in
float64: through the eikonal tracer's continuous and discrete adjoints and through sharp
interfaces."""

from __future__ import annotations

import numpy as np
import pytest

from clrefract.fields.base import Box
from clrefract.fields.interface import SphereInterface
from clrefract.fields.voxel import VoxelGrid
from clrefract.gradcheck import lens_scene
from clrefract.gradient import GradientEngine
from clrefract.interface import InterfaceEngine
from clrefract.tracer import TraceSettings

BOX = Box(margin=4.0)


def camera_shift_errors(eng, o, d, target, env, h):
    """Per axis, the summed origin gradient of all rays (one camera moved) against the central
    difference of the loss with every origin moved by h along that axis."""
    res = eng.loss_and_grad(o, d, target, env)
    total = res.origin_grad.sum(0)
    out = []
    for k in range(3):
        shift = np.zeros(3)
        shift[k] = h
        lp = eng.loss_and_grad(o + shift, d, target, env).loss
        lm = eng.loss_and_grad(o - shift, d, target, env).loss
        fd = (lp - lm) / (2 * h)
        out.append((fd, total[k]))
    return np.array(out), res


@pytest.mark.parametrize("adjoint", ["continuous", "discrete"])
def test_the_eikonal_origin_gradient_matches_central_differences(adjoint):
    """The noisy lens differs from 1 at the box's walls, where each ray's entry point slides
    on the wall it enters as its origin moves: without that term the component along the
    rays is 6% off."""
    vals, o, d, env, target = lens_scene()
    field = VoxelGrid(vals, BOX, "smoothstep")
    settings = TraceSettings(step=0.5, precision="float64", lanes=4, adjoint=adjoint)
    pairs, res = camera_shift_errors(GradientEngine(field, BOX, settings), o, d, target, env, 1e-6)
    fd, adj = pairs[:, 0], pairs[:, 1]
    assert np.all(np.abs(fd) > 1e-6), fd
    # measured: 6e-6 (continuous, its discretisation error), 4e-6 (discrete, the difference's)
    assert np.all(np.abs(adj - fd) <= 1e-4 * np.abs(fd)), pairs
    # rays that left no mark on the loss carry none: missed rays give exactly zero
    assert np.all(res.origin_grad[res.status != 0] == 0)


def test_the_interface_origin_gradient_matches_central_differences():
    """A glass sphere off the axis: every camera shift moves every crossing, with the point
    and normal of each (the implicit hit point) carried back to the origin."""
    _, o, d, env, target = lens_scene()
    field = SphereInterface((1.0, -2.0, 3.0), 20.0, 1.5, BOX)
    eng = InterfaceEngine(field, BOX, TraceSettings(precision="float64"), grazing_cos=0.0)
    pairs, res = camera_shift_errors(eng, o, d, target, env, 1e-6)
    fd, adj = pairs[:, 0], pairs[:, 1]
    assert np.all(np.abs(fd) > 1e-6), fd
    assert np.all(np.abs(adj - fd) <= 1e-5 * np.abs(fd)), pairs  # measured 1e-6
    # a ray that misses the sphere sees the environment along its own direction: no origin
    missed = np.linalg.norm(np.cross(o - [1.0, -2.0, 3.0], d), axis=1) > 20.5
    assert missed.any() and np.all(res.origin_grad[missed] == 0)
