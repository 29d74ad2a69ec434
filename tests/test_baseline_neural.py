"""The Meridian-style neural field (clrefract.baselines.neural): the device against the float64
NumPy reference, its gradient against central differences, the host compositing against a
closed form, and its file."""

import numpy as np
import pytest

from clrefract.baselines.composite import composite, ray_samples
from clrefract.baselines.neural import NeuralField, NeuralModel, NeuralRenderer
from clrefract.errors import ClrefractError
from clrefract.fields.base import Box
from clrefract.fields.hashgrid import HashGridConfig

# two hidden layers and a hashed finest level: every path of the kernels is used
SHAPE = HashGridConfig(
    levels=3, features=2, log2_table=9, n_min=4, n_max=16, hidden=8, layers=2, interp="trilinear"
)


@pytest.fixture(scope="module")
def field():
    rng = np.random.default_rng(0)
    f = NeuralField(SHAPE, Box(), seed=1)
    assert not all(SHAPE.dense)
    n_tab = SHAPE.n_table_params
    f.params[:n_tab] = rng.uniform(-1, 1, n_tab)  # features that matter, not instant-ngp's 1e-4
    f.params[n_tab:] += rng.normal(size=f.n_params - n_tab) * 0.3
    return f


def _rays(n, rng):
    """Rays from a sphere of radius 200 mm aimed near the origin (some miss the box)."""
    o = rng.normal(size=(n, 3))
    o *= 200 / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.normal(size=(n, 3)) * 30 - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("precision, tol", [("float64", 1e-12), ("float32", 2e-6)])
def test_device_field_matches_the_numpy_reference(field, precision, tol):
    pts = np.random.default_rng(1).uniform(-55, 55, (1000, 3))  # some outside the box
    sigma, rgb = NeuralRenderer(field, 3.0, precision).eval(pts)
    ref_sigma, ref_rgb = field.reference(pts)
    assert ref_rgb.std() > 0.05 and ref_sigma.max() > 2 * ref_sigma.min()  # not a flat field
    assert np.abs(sigma - ref_sigma).max() < tol
    assert np.abs(rgb - ref_rgb).max() < tol


def test_point_gradient_matches_central_differences(field):
    rng = np.random.default_rng(2)
    pts = rng.uniform(-50, 50, (500, 3))
    a, b = rng.normal(size=500), rng.normal(size=(500, 3))  # J = sum a sigma + b . rgb
    g = NeuralRenderer(field, 3.0, "float64").eval_backward(pts, a, b)

    def J(p):
        s, c = field.reference(pts, p)
        return (a * s).sum() + (b * c).sum()

    h, p0 = 1e-5, field.params.copy()
    n_tab = SHAPE.n_table_params
    u = rng.uniform(-1, 1, field.n_params)
    for part in (slice(0, n_tab), slice(n_tab, None)):  # tables, then the MLP
        v = np.zeros_like(u)
        v[part] = u[part]
        fd = (J(p0 + h * v) - J(p0 - h * v)) / (2 * h)
        assert abs(fd) > 1e-3
        assert g @ v == pytest.approx(fd, rel=1e-7)


def test_render_gradient_matches_central_differences(field):
    rng = np.random.default_rng(3)
    o, d = _rays(64, rng)
    bg = rng.uniform(0, 2, (64, 3))
    w = rng.normal(size=(64, 3))  # J = sum w . C
    r = NeuralRenderer(NeuralField(SHAPE, Box(), field.params), 3.0, "float64")
    p0 = r.field.params.copy()
    colour, left = r.render(o, d, bg)
    assert left.min() < 0.5 and left.max() == 1.0  # rays that see the field, and misses
    g = r.backward(o, d, bg, colour, w)

    def J(p):
        r.upload(p)
        return float((r.render(o, d, bg)[0] * w).sum())

    u, h = rng.uniform(-1, 1, len(p0)), 1e-5
    fd = (J(p0 + h * u) - J(p0 - h * u)) / (2 * h)
    assert g @ u == pytest.approx(fd, rel=1e-7)


def test_compositing_a_uniform_slab_is_beer_lambert():
    """Constant density and colour along a 100 mm chord: C = (1 - e^-sL) c + e^-sL bg."""
    o = np.array([[0.0, 0.0, -200.0], [0.0, 30.0, -200.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    s = ray_samples(o, d, Box(), 3.0)
    assert np.allclose(np.diff(s.starts), 34) and np.allclose(s.dt, 100 / 34)  # ceil(100 / 3)
    c, bg = np.array([0.2, 0.5, 0.9]), np.array([[1.0, 0.0, 2.0]] * 2)
    sigma = np.full(len(s.points), 0.02)
    colour, left = composite(sigma, np.tile(c, (len(sigma), 1)), s, bg)
    t = np.exp(-0.02 * 100)
    assert left == pytest.approx([t, t], rel=1e-12)
    assert np.allclose(colour, (1 - t) * c + t * bg, rtol=0, atol=1e-12)
    miss = ray_samples(np.array([[0.0, 0.0, -200.0]]), np.array([[1.0, 0.0, 0.0]]), Box(), 3.0)
    assert len(miss.points) == 0
    assert composite(np.zeros(0), np.zeros((0, 3)), miss, bg[:1])[1][0] == 1.0


def test_saved_model_renders_the_same_and_damage_is_one_line(field, tmp_path):
    from clrefract.baselines.straight import load_straight

    m = NeuralModel(NeuralField(SHAPE, Box(), field.params), 3.0, surface_res=24)
    m.save(tmp_path / "straight.npz")
    back = load_straight(tmp_path / "straight.npz")
    assert isinstance(back, NeuralModel) and back.surface_res == 24
    pts = np.random.default_rng(4).uniform(-40, 40, (50, 3))
    assert np.array_equal(back.density(pts), m.density(pts))
    bad = tmp_path / "bad.npz"
    bad.write_bytes((tmp_path / "straight.npz").read_bytes()[:200])
    with pytest.raises(ClrefractError, match="bad.npz: cannot read"):
        load_straight(bad)


def test_meridian_is_neural_by_default_and_a_bad_field_is_refused():
    from clrefract.baselines.straight import StraightConfig

    assert StraightConfig(style="meridian").resolved().field == "neural"
    assert StraightConfig(style="meridian", field="grid").resolved().res == 48
    with pytest.raises(ClrefractError, match="field must be one of grid, neural"):
        StraightConfig(style="meridian", field="mlp").resolved()
