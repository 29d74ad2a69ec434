"""A medium that the box cuts: `dataset check` and the fit's start say so in one line, with
the --box that would hold it (clrefract.box_walls); a medium inside the box is not reported."""

from __future__ import annotations

import io
import json
import re

import numpy as np
import pytest

from clrefract.box_walls import box_walls
from clrefract.cli import main
from clrefract.dataset import Dataset, box_of, check_dataset
from clrefract.fields.analytic import Blobs
from clrefract.fields.base import Box
from clrefract.hull import refraction_mask
from clrefract.synth import MakeOptions, make_dataset

SMALL = {"views": 12, "res": 24, "env_width": 512, "volume_res": 8}
# two blobs; the upper one's centre 14 mm below the +z wall of the default box (+-50 mm),
# where its index is still a fifth of its peak above 1
CLUSTER = Blobs(centers=[[0, 0, 36], [-8, 4, 20]], amplitudes=[0.05, 0.03], sigmas=[8, 6])
CENTRED = Blobs(centers=[[0, 0, 0]], amplitudes=[0.05], sigmas=[8])


def _made(tmp_path_factory, name: str, obj):
    root = tmp_path_factory.mktemp("walls") / name
    make_dataset(name, root, MakeOptions(**SMALL), obj=obj)
    return root


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    return _made(tmp_path_factory, "cluster", CLUSTER)


def _warnings(notes: list[str]) -> list[str]:
    return [n for n in notes if n.startswith("warning: ")]


def _suggested(line: str) -> Box:
    return box_of(re.search(r"--box (\S+)", line).group(1))


def _top(obj, share: float = 1e-3) -> float:
    """The highest z (mm) where eta - 1 exceeds `share` of its peak."""
    ax = np.arange(-40.0, 41.0, 2.0)
    z = np.arange(-60.0, 120.0, 0.5)
    pts = np.stack(np.meshgrid(ax, ax, z, indexing="ij"), axis=-1).reshape(-1, 3)
    rise = obj.eval(pts)[0] - 1
    return float(pts[rise > share * rise.max(), 2].max())


def test_a_cluster_cut_by_a_wall_is_reported_with_a_box_that_holds_it(cluster, capsys):
    notes: list[str] = []
    assert check_dataset(cluster, notes) == []
    (line,) = _warnings(notes)
    assert "reaches the box's +z wall (z = 50)" in line, line
    box, default = _suggested(line), Box()
    assert box.hi[2] >= _top(CLUSTER) > default.hi[2], (box, _top(CLUSTER))
    # the other walls stay where they were
    assert box.lo == default.lo and box.hi[:2] == default.hi[:2]
    # the command line prints it as one note naming the folder; the data is fine (status 0)
    assert main(["dataset", "check", str(cluster)]) == 0
    out = capsys.readouterr().out.splitlines()
    said = [ln for ln in out if "reaches the box" in ln]
    assert said == [f"{cluster}: {line}"], out
    assert out[-1] == f"{cluster}: OK"
    # checked in the box it suggests, the same data reaches no wall
    notes = []
    assert check_dataset(cluster, notes, box=box) == [] and not _warnings(notes), notes


def test_a_centred_medium_and_a_glass_sphere_are_not_reported(tmp_path_factory, sphere_12x24):
    for root in (_made(tmp_path_factory, "centred", CENTRED), sphere_12x24):
        notes: list[str] = []
        assert check_dataset(root, notes) == [] and not _warnings(notes), (root, notes)


def test_a_box_that_cuts_the_sphere_is_reported_on_every_side(sphere_12x24):
    """--box around the sphere (radius 20 mm) but tighter: every wall is reached."""
    ds = Dataset(sphere_12x24, box=box_of("-24,-24,-24,24,24,24"))
    env = ds.envmap()
    masks = [refraction_mask(c, ds.image(c), env) for c in ds.train]
    walls = box_walls(ds.box, ds.train, masks)
    assert walls is not None and len(walls.sides) == 6, walls
    lo, hi = np.asarray(walls.suggested.lo), np.asarray(walls.suggested.hi)
    assert np.all(lo <= -20 - 8) and np.all(hi >= 20 + 8), walls.suggested


def test_the_fit_start_says_so_and_run_json_records_it(cluster, tmp_path):
    from clrefract.fit import load_config
    from clrefract.fit.session import prepare_fit

    keys = {"iterations": 1, "res": 8, "step": 4.0, "field": "voxel", "init": "empty"}
    stream = io.StringIO()
    prepare_fit(cluster, tmp_path / "run", load_config(None, keys), stream=stream)
    said = [ln for ln in stream.getvalue().splitlines() if "reaches the box" in ln]
    assert len(said) == 1 and said[0].startswith(f"warning: {cluster}: the medium reaches")
    assert "+z wall" in said[0] and "--box -50,-50,-50,50,50," in said[0], said
    meta = json.loads((tmp_path / "run" / "run.json").read_text())
    walls = meta["box_walls"]
    assert walls["sides"] == ["+z"] and meta["box"] == Box().to_dict(), meta
    assert Box.from_dict(walls["suggested_box"]) == _suggested(said[0])
