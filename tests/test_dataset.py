"""Datasets: generated, written and read back identically, checked for every kind of damage;
the eikonal tracer converging to the exact Snell ground truth at a sharp interface."""

import json
import shutil

import numpy as np
import pytest

from clrefract.cli import main
from clrefract.dataset import Dataset, check_dataset
from clrefract.fields.analytic import Sphere
from clrefract.imageio import read_exr_rgb, write_exr_rgb
from clrefract.mesh import read_mesh
from clrefract.snell import SnellRenderer
from clrefract.synth import MakeOptions, make_dataset, scene_object
from clrefract.tracer import Tracer, TraceSettings


@pytest.fixture
def sphere_ds(sphere_10x24):
    """The 10-view 24 x 24 sphere that tests/conftest.py makes once; read-only (a test that
    damages it copies it first)."""
    return sphere_10x24


def test_dataset_has_the_protocol_layout(sphere_ds):
    root = sphere_ds
    ds = Dataset(root)
    assert len(ds.train) == 8 and len(ds.test) == 2  # views 0 and 5 are held out
    assert [c.name for c in ds.test] == ["r_000", "r_005"]
    scene = json.loads((root / "scene.json").read_text())
    assert scene["object"]["kind"] == "sphere" and scene["eta_range"] == [1.0, 1.5]
    assert scene["ground_truth"]["renderer"] == "snell"
    verts, faces = read_mesh(root / "gt_surface.ply")
    r = np.linalg.norm(verts, axis=1)
    assert np.abs(r - 20.0).max() < 0.2 and len(faces) > 1000
    assert check_dataset(root) == []


def test_images_are_the_snell_ground_truth_and_read_back_identically(sphere_ds, tmp_path):
    root = sphere_ds
    ds = Dataset(root)
    cam = ds.train[0]
    o, d = cam.rays()
    res = SnellRenderer(Sphere(radius=20.0, eta=1.5)).trace(o, d)
    expect = ds.envmap().lookup(res.direction).reshape(cam.height, cam.width, 3)
    assert np.array_equal(ds.image(cam), expect)
    # written and read back: identical
    img = ds.image(cam)
    tmp = tmp_path / "copy.exr"
    write_exr_rgb(tmp, img)
    assert np.array_equal(read_exr_rgb(tmp), img)


def _broken(root, tmp_path, name):
    dst = tmp_path / name
    shutil.copytree(root, dst)
    return dst


def test_check_names_every_problem(sphere_ds, tmp_path):
    root = sphere_ds
    # a missing frame
    ds1 = _broken(root, tmp_path, "missing")
    (ds1 / "train" / "r_001.exr").unlink()
    assert any("r_001.exr is missing" in p for p in check_dataset(ds1))
    # an image of the wrong size
    ds2 = _broken(root, tmp_path, "size")
    write_exr_rgb(ds2 / "train" / "r_002.exr", np.zeros((10, 12, 3), np.float32))
    assert any("r_002.exr: image is 12x10" in p for p in check_dataset(ds2))
    # non-finite pixels
    ds3 = _broken(root, tmp_path, "nan")
    img = read_exr_rgb(ds3 / "test" / "r_005.exr")
    img[3, 4] = np.nan
    write_exr_rgb(ds3 / "test" / "r_005.exr", img)
    assert any("r_005.exr: 1 pixel(s) with non-finite" in p for p in check_dataset(ds3))
    # an unreadable EXR
    ds4 = _broken(root, tmp_path, "garbage")
    (ds4 / "train" / "r_003.exr").write_bytes(b"not an exr at all")
    assert any("r_003.exr" in p for p in check_dataset(ds4))
    # a camera looking away from the box
    ds5 = _broken(root, tmp_path, "away")
    tj = json.loads((ds5 / "transforms_train.json").read_text())
    m = np.array(tj["frames"][0]["transform_matrix"])
    m[:3, 2] *= -1  # now it looks outward
    m[:3, 0] *= -1
    tj["frames"][0]["transform_matrix"] = m.tolist()
    (ds5 / "transforms_train.json").write_text(json.dumps(tj))
    assert any("does not look at the box" in p for p in check_dataset(ds5))
    # malformed camera JSON
    ds6 = _broken(root, tmp_path, "json")
    (ds6 / "transforms_test.json").write_text("{ not json")
    assert any("transforms_test.json: not valid JSON" in p for p in check_dataset(ds6))


def test_dataset_check_cli_exit_codes(sphere_ds, tmp_path, capsys):
    root = sphere_ds
    assert main(["dataset", "check", str(root)]) == 0
    assert "OK" in capsys.readouterr().out
    assert main(["dataset", "check", str(tmp_path / "nowhere")]) == 2  # bad input
    assert "not found" in capsys.readouterr().out


def test_dataset_check_box_option(sphere_ds, tmp_path, capsys):
    """--box replaces scene.json's box (and the cameras' without one), and check says so."""
    root = sphere_ds
    assert main(["dataset", "check", str(root), "--box", "-30,-30,-30,30,30,30"]) == 0
    out = capsys.readouterr().out
    assert "box from --box: [-30, -30, -30] to [30, 30, 30] mm, margin 4" in out
    # a box far from where the cameras look: every camera is named, status 2
    assert (
        main(["dataset", "check", str(root), "--box", "500", "500", "500", "600", "600", "600"])
        == 2
    )
    out = capsys.readouterr().out
    assert out.count("camera does not look at the box") == 10 and "box from --box" in out
    bare = tmp_path / "bare"
    shutil.copytree(root, bare)
    (bare / "scene.json").unlink()
    assert main(["dataset", "check", str(bare), "--box=-30,-30,-30,30,30,30"]) == 0
    out = capsys.readouterr().out
    assert "box from --box" in out and "box from the cameras" not in out
    assert "assumed box" not in out and "assumed no scene.json" in out


def test_render_accepts_a_dataset(sphere_ds, tmp_path):
    root = sphere_ds
    out = tmp_path / "r"
    assert (
        main(["render", "--dataset", str(root), "--field", "sphere:width=0.5", "--out", str(out)])
        == 0
    )
    assert sorted(p.name for p in out.glob("*.exr")) == ["r_000.exr", "r_005.exr"]


@pytest.mark.parametrize("name", ["prism", "drop"])
def test_other_solids_generate_and_check(name, tmp_path):
    info = make_dataset(name, tmp_path, MakeOptions(views=5, res=16, env_width=128, volume_res=12))
    assert info["views"] == 5 and check_dataset(tmp_path) == []


def _eikonal_exit_error(width, step):
    """Angle (rad) between the eikonal and the Snell exit directions through a sphere."""
    rng = np.random.default_rng(0)
    b = 20.0 * np.sqrt(rng.uniform(0, 0.8**2, 300))  # impact parameters up to 0.8 R
    phi = rng.uniform(0, 2 * np.pi, 300)
    o = np.column_stack([b * np.cos(phi), b * np.sin(phi), np.full(300, -120.0)])
    d = np.tile([0.0, 0.0, 1.0], (300, 1))
    exact = SnellRenderer(Sphere(radius=20.0, eta=1.5)).trace(o, d).direction
    eik = (
        Tracer(
            Sphere(radius=20.0, eta=1.5, width=width),
            settings=TraceSettings(step=step, precision="float64"),
        )
        .trace(o, d)
        .direction
    )
    return float(np.arccos(np.clip((exact * eik).sum(1), -1, 1)).max())


def test_eikonal_tracer_converges_to_snell_as_interface_and_step_shrink():
    errs = [_eikonal_exit_error(w, w / 8) for w in (2.0, 1.0, 0.5)]
    assert errs[0] > errs[1] > errs[2], errs
    assert errs[2] < 5e-3
    assert errs[0] / errs[2] > 3


def test_prism_scene_is_tilted_away_from_every_camera():
    from clrefract.cameras import fibonacci_sphere_cameras
    from clrefract.fields.analytic import rotation_xyz

    prism = scene_object("prism")
    axis = rotation_xyz(prism.tilt)[:, 2]
    for cam in fibonacci_sphere_cameras(100):
        view = cam.c2w[:3, 2]
        assert abs(view @ axis) < np.cos(np.radians(5))
