"""Empty-space skipping (issue 12): rays fly straight through cells where eta is constant;
same exit rays to rounding, far fewer integration steps when the object is small."""

import numpy as np
import pytest

from clrefract.errors import ClrefractError
from clrefract.fields.analytic import Luneburg, Sphere
from clrefract.fields.base import Box
from clrefract.fields.voxel import VoxelGrid
from clrefract.occupancy import occupied_cells
from clrefract.tracer import Tracer


def _rays(n=256, seed=0):
    rng = np.random.default_rng(seed)
    o = np.column_stack([np.full(n, -120.0), rng.uniform(-12, 12, (n, 2))])
    d = np.column_stack([np.ones(n), rng.normal(0, 0.02, (n, 2))])
    return o, d


@pytest.mark.parametrize(
    "field,step",
    [(Sphere(radius=10.0, eta=1.5, width=1.0), 0.125), (Luneburg(radius=10.0), 0.25)],
)
def test_same_rays_with_fewer_steps(field, step):
    o, d = _rays()
    a = Tracer(field, step=step, precision="float64").trace(o, d)
    b = Tracer(field, step=step, precision="float64", skip_empty=True).trace(o, d)
    assert np.array_equal(a.status, b.status)
    assert np.abs(a.direction - b.direction).max() < 1e-9
    assert np.abs(a.position - b.position).max() < 1e-7
    assert b.steps.mean() < a.steps.mean() / 3


def test_voxel_grid_skipping_matches_but_for_chaotic_rays():
    """A voxel sphere whose band grazing rays orbit chaotically: those may differ by
    rounding amplified; the rest match to 1e-6."""
    vox = VoxelGrid.from_field(Sphere(radius=10.0, eta=1.5, width=2.0), res=33)
    o, d = _rays(128)
    kw = dict(box=vox.box, step=0.5, precision="float64")
    a = Tracer(vox, **kw).trace(o, d)
    b = Tracer(vox, skip_empty=True, **kw).trace(o, d)
    off = np.abs(a.direction - b.direction).max(1) > 1e-6
    assert off.mean() < 0.03, off.mean()
    assert b.steps.mean() < a.steps.mean() / 2


def test_occupancy_covers_a_thin_interface():
    """A band 0.05 mm thick, far thinner than the samples (0.78 mm): every cell that the
    sphere's surface passes through is occupied."""
    f = Sphere(radius=20.0, eta=1.5, width=0.05)
    occ = occupied_cells(f, Box(), res=32, dilate=0)
    rng = np.random.default_rng(0)
    p = rng.normal(size=(2000, 3))
    p = 20.0 * p / np.linalg.norm(p, axis=1, keepdims=True)
    cells = np.floor((p + 50.0) / (100.0 / 32)).astype(int)
    assert occ[cells[:, 0], cells[:, 1], cells[:, 2]].all()


def test_skipping_is_forward_only():
    vox = VoxelGrid(np.ones((8, 8, 8)))
    with pytest.raises(ClrefractError, match="forward only"):
        Tracer(vox, box=vox.box, skip_empty=True, adjoint=True)
