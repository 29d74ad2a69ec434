"""A voxel grid's start grades the visual hull of a graded medium from its surface inwards,
and fills the hull of glass solid: the start's loss chooses."""

from __future__ import annotations

import json

import numpy as np
import pytest


def test_a_graded_hull_rises_from_its_surface_to_its_deepest_point_by_its_power():
    """On a ball's signed distance (radius R, a node at its centre) the profile of power p is
    1 - (r / R)^p... of the depth: 1 - (1 - (R - r) / R)^p = 1 - (r / R)^p, 0 outside; the
    occupancy stays the solid hull's."""
    from clrefract.hull import Hull

    x = np.linspace(-25.0, 25.0, 51)
    r = np.linalg.norm(np.stack(np.meshgrid(x, x, x, indexing="ij")), axis=0)
    hull = Hull(distance=20.0 - r, width=1.0, mask_fraction=0.1)
    inside = r <= 20.0
    for power in (1.0, 2.0, 4.0):
        graded = hull.graded(power)
        shell = graded.shell()
        assert np.allclose(shell[inside], 1 - (r[inside] / 20.0) ** power, atol=1e-12)
        assert np.all(shell[~inside] == 0.0)
        assert np.array_equal(graded.occupancy, hull.occupancy)
    # grown by 5 mm: a ball of 25 mm graded the same way
    grown = hull.graded(2.0).shell(5.0)
    assert np.allclose(grown[r <= 25], 1 - (r[r <= 25] / 25.0) ** 2, atol=1e-12)


def _start(data, run, **over) -> tuple[dict, list]:
    from clrefract.fit import load_config, prepare_fit

    cfg = load_config(None, dict(field="voxel", res=24, iterations=1, **over))
    prepare_fit(data, run, cfg, stream=open("/dev/null", "w"))
    info = json.loads((run / "init.json").read_text())
    losses = [json.loads(line) for line in (run / "start_losses.jsonl").open()]
    return info, [row for row in losses if "key" in row]


@pytest.fixture(scope="module")
def luneburg_16x32(tmp_path_factory):
    from clrefract.synth import MakeOptions, make_dataset

    out = tmp_path_factory.mktemp("graded") / "luneburg"
    make_dataset("luneburg", out, MakeOptions(views=16, res=32), stream=open("/dev/null", "w"))
    return out


def test_a_luneburg_lens_starts_graded_near_its_true_index(luneburg_16x32, tmp_path):
    """The Luneburg lens (index sqrt 2 at its centre, 1 at its edge): the hull graded from
    its surface beats every solid fill's loss, at a top index within 0.03 of sqrt 2, where
    the solid fill's best is in a shrunken hull."""
    info, losses = _start(luneburg_16x32, tmp_path / "run")
    assert info["graded_power"] > 0 and info["offset_mm"] == 0.0, info
    assert abs(info["eta"] - np.sqrt(2)) < 0.03, info
    solid = min(losses, key=lambda row: row["loss"] if row["key"].startswith("visual|") else 1)
    assert info["loss"] < solid["loss"], (info, solid)
    assert float(solid["key"].split("|")[2]) < 0, solid  # key: shape|index|offset


def test_glass_starts_solid(sphere_10x24, tmp_path):
    """A glass sphere of index 1.5: the solid hull's fill beats every graded one."""
    info, losses = _start(sphere_10x24, tmp_path / "run")
    assert info["graded_power"] == 0.0, info
    graded = min(row["loss"] for row in losses if row["key"].startswith("graded"))
    assert info["loss"] < graded, (info, graded)
