"""Environment map lookup (SPEC section 6) and the procedural default."""

import numpy as np
import pytest

from clrefract.envmap import EnvMap, pixel_directions
from clrefract.errors import ClrefractError
from clrefract.imageio import write_exr_rgb


def _dir(u, v):
    """Unit direction for equirect coordinates u, v in [0, 1] (inverse of SPEC section 6)."""
    phi = (np.asarray(u) - 0.5) * 2 * np.pi
    theta = np.asarray(v) * np.pi
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def _coord_map(w=8, h=4):
    """Channel 0 = column index, channel 1 = row index, channel 2 = 1."""
    img = np.zeros((h, w, 3), np.float32)
    img[..., 0] = np.arange(w)[None, :]
    img[..., 1] = np.arange(h)[:, None]
    img[..., 2] = 1
    return EnvMap(img)


def test_lookup_at_pixel_centres_is_exact():
    env = _coord_map()
    rows, cols = np.meshgrid(np.arange(4), np.arange(8), indexing="ij")
    d = _dir((cols.ravel() + 0.5) / 8, (rows.ravel() + 0.5) / 4)
    out = env.lookup(d)
    np.testing.assert_allclose(out[:, 0], cols.ravel(), atol=1e-5)
    np.testing.assert_allclose(out[:, 1], rows.ravel(), atol=1e-5)
    np.testing.assert_allclose(env.lookup(pixel_directions(8, 4).reshape(-1, 3)), out, atol=1e-6)


def test_lookup_bilinear_between_centres_and_unnormalised():
    env = _coord_map()
    # col = u W - 0.5 = 2.25, row = v H - 0.5 = 1.75
    d = _dir((2.25 + 0.5) / 8, (1.75 + 0.5) / 4)[None] * 37.0
    out = env.lookup(d)[0]
    assert out[0] == pytest.approx(2.25, abs=1e-5)
    assert out[1] == pytest.approx(1.75, abs=1e-5)
    assert out[2] == pytest.approx(1.0, abs=1e-6)


def test_lookup_axes_follow_spec():
    env = _coord_map()
    # +x: u = 0.5 -> col 3.5; -x: u = 0 or 1 -> seam; +y: u = 0.75 -> col 5.5; +z: top row.
    out = env.lookup(np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, -1.0]]))
    assert out[0, 0] == pytest.approx(3.5) and out[0, 1] == pytest.approx(1.5)
    assert out[1, 0] == pytest.approx(5.5)
    assert out[2, 1] == pytest.approx(0.0) and out[3, 1] == pytest.approx(3.0)


def test_lookup_wraps_across_u_seam():
    env = _coord_map()
    # col = -0.25 lies between column 7 (weight 0.25) and column 0 (weight 0.75).
    for u in (-0.25 + 0.5) / 8, 1 + (-0.25 + 0.5) / 8:
        out = env.lookup(_dir(u, 0.5)[None])[0]
        assert out[0] == pytest.approx(0.25 * 7 + 0.75 * 0, abs=1e-5)
    # Exactly on the seam (direction -x): halfway between last and first columns.
    out = env.lookup(np.array([[-1.0, 1e-15, 0.0], [-1.0, -1e-15, 0.0]]))
    np.testing.assert_allclose(out[:, 0], 3.5, atol=1e-5)


def test_lookup_clamps_at_poles():
    env = _coord_map()
    # Within half a pixel of the poles there is nothing to blend with: edge rows repeat.
    out = env.lookup(np.array([[0, 0, 1.0], [1e-3, 0, 1.0], [0, 0, -1.0], [1e-3, 0, -1.0]]))
    np.testing.assert_allclose(out[:, 1], [0, 0, 3, 3], atol=1e-6)
    assert np.isfinite(env.lookup(np.zeros((1, 3)))).all()


def test_procedural_deterministic_hdr_and_detailed():
    a = EnvMap.procedural(256, 128, seed=3)
    b = EnvMap.procedural(256, 128, seed=3)
    c = EnvMap.procedural(256, 128, seed=4)
    assert a.image.shape == (128, 256, 3) and a.image.dtype == np.float32
    np.testing.assert_array_equal(a.image, b.image)
    assert np.abs(a.image - c.image).mean() > 0.05
    img = a.image
    assert np.isfinite(img).all() and img.min() > 0
    assert 5.0 <= img.max() <= 50.0 + 1e-3  # lamps
    assert (img > 1).mean() < 0.2  # but mostly moderate
    # Detail everywhere: no 16x16 block in which neighbouring pixels are (nearly) equal.
    g = np.abs(np.diff(img, axis=0))[:, :-1].mean(-1) + np.abs(np.diff(img, axis=1))[:-1].mean(-1)
    g = g[:112, :240].reshape(7, 16, 15, 16).mean(axis=(1, 3))
    assert g.min() > 0.005
    # Smooth enough for bilinear lookup: typical neighbour steps are a few percent of the value.
    rel = np.abs(np.diff(img, axis=0)) / img[1:]
    assert 0.01 < np.median(rel) < 0.15


def test_procedural_default_size_against_a_float64_reference():
    """The default map, computed in float32 and in chunks of 64 rows, against the same
    construction in float64 (the seed's waves, checker and lamps) on every 16th row and
    the rows either side of each chunk boundary. Measured: 3.6e-6 relative away from the
    lamps' edges (float32 sines), 2.8e-4 on them (float32 arccos near 1 moves the edge)."""
    from clrefract.envmap import checker_and_grid

    env = EnvMap.procedural()
    assert env.image.shape == (512, 1024, 3) and env.image.dtype == np.float32
    w, h = 1024, 512
    rng = np.random.default_rng(0)  # the draws of procedural_image, in its order
    octaves = 2.0 ** np.arange(1, 12)
    n = len(octaves) * 10
    k = rng.normal(size=(n, 3))
    k /= np.linalg.norm(k, axis=1, keepdims=True)
    freq = np.repeat(octaves, 10) * 2.0 ** rng.uniform(0, 1, n)
    phase = rng.uniform(0, 2 * np.pi, n)
    colour = rng.normal(size=(n, 3)) * (freq**-0.3)[:, None]
    colour /= np.sqrt(0.5 * (colour**2).sum(axis=0))
    lamp = rng.normal(size=(5, 3))
    lamp /= np.linalg.norm(lamp, axis=1, keepdims=True)
    radius = np.deg2rad(rng.uniform(1.5, 4.0, 5))
    value = rng.uniform(5.0, 50.0, 5)
    tint = rng.uniform(0.6, 1.0, (5, 3))
    tint /= tint.max(axis=1, keepdims=True)
    keep = freq <= w / 5  # waves of 5 pixels or more
    rows = np.unique(np.r_[np.arange(0, h, 16), np.arange(63, h, 64), np.arange(64, h, 64)])
    d = pixel_directions(w, h)[rows]
    noise = np.sin(d @ (k[keep] * freq[keep, None]).T + phase[keep]) @ colour[keep]
    want = 0.35 * np.exp(0.6 * noise) * checker_and_grid(w, h)[rows][..., None]
    ang = np.arccos(np.clip(d @ lamp.T, -1.0, 1.0))
    edge_px = 2 * np.pi / w
    want += (0.5 * (1 - np.tanh((ang - radius) / edge_px)) * value) @ tint
    err = np.abs(env.image[rows] - want) / want
    at_edge = (np.abs(ang - radius) < 5 * edge_px).any(-1)
    assert at_edge.sum() > 100 and want.max() > 5  # lamps lie on the rows checked
    assert err[~at_edge].max() < 3e-5, err[~at_edge].max()
    assert err[at_edge].max() < 2e-3, err[at_edge].max()


def test_blurred_wraps_and_keeps_mean():
    env = EnvMap.procedural(128, 64, seed=0)
    bl = env.blurred(3.0)
    assert bl.image.shape == env.image.shape
    assert bl.image.mean() == pytest.approx(env.image.mean(), rel=1e-2)
    assert np.abs(np.diff(bl.image, axis=1)).mean() < np.abs(np.diff(env.image, axis=1)).mean()
    # Wrap: a spike in the first column spreads into the last.
    img = np.zeros((16, 32, 3), np.float32)
    img[8, 0] = 1
    out = EnvMap(img).blurred(1.0).image
    assert out[8, -1, 0] == pytest.approx(out[8, 1, 0], rel=1e-5) and out[8, -1, 0] > 0.05


def test_save_and_from_exr(tmp_path):
    env = EnvMap.procedural(64, 32, seed=1)
    env.save(tmp_path / "env.exr")
    np.testing.assert_array_equal(EnvMap.from_exr(tmp_path / "env.exr").image, env.image)


def test_from_exr_rejects_non_finite(tmp_path):
    img = np.ones((4, 8, 3), np.float32)
    img[1, 1, 1] = np.inf
    write_exr_rgb(tmp_path / "bad.exr", img)
    with pytest.raises(ClrefractError, match="bad.exr"):
        EnvMap.from_exr(tmp_path / "bad.exr")
