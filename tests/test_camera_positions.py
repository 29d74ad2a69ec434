"""`clrefract dataset refine-positions`: camera centres recorded a known distance off the true
ones (realistic.py's pose flaw), moved back by fitting renders of the true sphere."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from clrefract.camera_positions import estimate_offsets
from clrefract.cameras import load_transforms
from clrefract.cli import main
from clrefract.dataset import Dataset
from clrefract.fields.interface import InterfaceField, SphereInterface
from clrefract.interface import InterfaceTracer
from clrefract.realistic import TRUTH_FILE, parse_flaws
from clrefract.synth import MakeOptions, make_dataset

POSE_MM = 1.0  # half a pixel at the object (48 x 48 views, 2.2 mm a pixel)


@pytest.fixture(scope="module")
def moved(tmp_path_factory):
    """The sphere, 20 views of 48 x 48, each camera recorded POSE_MM from where it shot."""
    root = tmp_path_factory.mktemp("positions") / "sphere"
    opt = MakeOptions(views=20, res=48, env_width=512, volume_res=16)
    opt.realistic = parse_flaws(f"pose_mm={POSE_MM}")
    make_dataset("sphere", root, opt)
    return root


def true_positions(root) -> dict:
    truth = json.loads((root / TRUTH_FILE).read_text())
    return {f["file_path"]: np.asarray(f["transform_matrix"])[:3, 3] for f in truth["frames"]}


def in_plane_errors(cams, truth, offsets=None) -> np.ndarray:
    """(n, 2) each camera's position error along its right and up axes (mm)."""
    out = []
    for k, cam in enumerate(cams):
        e = cam.position - truth[cam.file_path]
        if offsets is not None:
            e = e + offsets[k]
        out.append(cam.c2w[:3, :2].T @ e)
    return np.array(out)


def rms(a) -> float:
    return float(np.sqrt(np.mean(np.sum(np.square(a), axis=1))))


def test_the_true_sphere_takes_each_camera_back(moved):
    """Against the true field the in-plane shift is recovered to a tenth of its size (the
    shift along the view is not sought: it scales the object by 0.5%)."""
    ds = Dataset(moved)
    field = SphereInterface((0.0, 0.0, 0.0), 20.0, 1.5, ds.box)
    offsets = estimate_offsets(ds, InterfaceTracer(field, ds.box))
    truth = true_positions(moved)
    before = in_plane_errors(ds.train, truth)
    after = in_plane_errors(ds.train, truth, [v.offset_mm for v in offsets])
    assert rms(before) > 0.5 * POSE_MM  # two of three directions of a random shift
    assert rms(after) < 0.1 * rms(before), (rms(before), rms(after))
    assert all(v.loss_after < v.loss_before for v in offsets)
    for v, cam in zip(offsets, ds.train, strict=True):  # in the image plane only
        assert abs(v.offset_mm @ cam.c2w[:3, 2]) < 1e-9


def sphere_run(run, box, res: int = 48) -> None:
    """A run folder holding only field.npz: the sphere of radius 20 as a B-spline interface."""
    axes = [np.linspace(box.lo[k], box.hi[k], res) for k in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    run.mkdir()
    InterfaceField(np.linalg.norm(pts, axis=-1) - 20.0, box, eta=1.5).save(run / "field.npz")


def strip_positions(doc: dict) -> dict:
    """The transforms file with the cameras' positions taken out."""
    doc = json.loads(json.dumps(doc))
    for fr in doc["frames"]:
        fr["transform_matrix"] = [row[:3] for row in fr["transform_matrix"]]
    return doc


def test_write_moves_the_training_cameras_and_nothing_else(moved, tmp_path, capsys):
    root = tmp_path / "data"
    shutil.copytree(moved, root)
    sphere_run(tmp_path / "run", Dataset(root).box)
    train_file, test_file = root / "transforms_train.json", root / "transforms_test.json"
    before, test_before = json.loads(train_file.read_text()), test_file.read_bytes()
    cams = load_transforms(train_file)
    assert main(["dataset", "refine-positions", str(root), "--run", str(tmp_path / "run")]) == 0
    assert json.loads(train_file.read_text()) == before  # without --write: nothing
    argv = ["dataset", "refine-positions", str(root), "--run", str(tmp_path / "run"), "--write"]
    assert main([*argv]) == 0
    capsys.readouterr()
    after = json.loads(train_file.read_text())
    assert strip_positions(after) == strip_positions(before)
    assert test_file.read_bytes() == test_before  # test views keep their recorded poses
    truth = true_positions(root)
    moved_cams = load_transforms(train_file)
    err0 = in_plane_errors(cams, truth)
    err1 = in_plane_errors(moved_cams, truth)
    assert rms(err1) < 0.3 * rms(err0), (rms(err0), rms(err1))
    for a, b in zip(cams, moved_cams, strict=True):
        np.testing.assert_array_equal(a.c2w[:3, :3], b.c2w[:3, :3])


def test_bad_input_is_refused_in_one_line_and_nothing_written(moved, tmp_path, capsys):
    train_file = moved / "transforms_train.json"
    before = train_file.read_bytes()
    (tmp_path / "empty").mkdir()
    for run in (tmp_path / "empty", tmp_path / "absent"):
        argv = ["dataset", "refine-positions", str(moved), "--run", str(run), "--write"]
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(run) in err, err
    sphere_run(tmp_path / "run", Dataset(moved).box)
    argv = ["dataset", "refine-positions", str(tmp_path / "nodata"), "--run", str(tmp_path / "run")]
    assert main(argv) == 2
    assert str(tmp_path / "nodata") in capsys.readouterr().err
    assert train_file.read_bytes() == before
