"""`clrefract eval`: each metric against a hand-computed case, and whole runs scored."""

import json
import math
import shutil

import numpy as np
import pytest

from clrefract.cli import main
from clrefract.evaluate import eta_rmse_of, evaluate_run
from clrefract.fields.analytic import Sphere
from clrefract.fields.base import Box
from clrefract.imageio import srgb_to_linear
from clrefract.metrics import chamfer_distance, psnr_ssim


@pytest.fixture
def sphere_data(sphere_10x24):
    """The 10-view 24 x 24 sphere that tests/conftest.py makes once; read-only."""
    return sphere_10x24


def _truth_run(root, data):
    """A finished run whose field is the truth sampled on a voxel grid."""
    from clrefract.fields.voxel import VoxelGrid
    from clrefract.synth import scene_object

    root.mkdir()
    VoxelGrid.from_field(scene_object("sphere"), Box(), 32, "trilinear").save(root / "field.npz")
    (root / "run.json").write_text(json.dumps({"dataset": str(data), "box": Box().to_dict()}))
    return root


@pytest.mark.filterwarnings("ignore:divide by zero")  # scikit-image's own 1/0 = inf
def test_identical_images_infinite_psnr_and_ssim_one():
    img = np.random.default_rng(0).random((24, 24, 3)) * 1.5  # HDR values clip alike
    psnr, ssim = psnr_ssim(img, img)
    assert math.isinf(psnr) and psnr > 0
    assert ssim == pytest.approx(1.0, abs=1e-12)


def test_psnr_of_a_constant_srgb_offset():
    # sRGB 0.5 against 0.6 everywhere: MSE 0.01, PSNR = -10 log10(0.01) = 20 dB
    a = np.full((16, 16, 3), srgb_to_linear(np.float32(0.5)))
    b = np.full((16, 16, 3), srgb_to_linear(np.float32(0.6)))
    assert psnr_ssim(a, b)[0] == pytest.approx(20.0, abs=1e-3)


def test_chamfer_of_concentric_spheres_is_the_radius_difference():
    import trimesh

    small = trimesh.creation.icosphere(subdivisions=5, radius=20.0)
    big = trimesh.creation.icosphere(subdivisions=5, radius=21.0)
    # the protocol's 100k samples: the nearest sample also sits a little to the side
    # (about 0.1 mm apart here), which adds well under 1% to the 1 mm
    d = chamfer_distance((small.vertices, small.faces), (big.vertices, big.faces))
    assert d == pytest.approx(1.0, abs=0.015)


def test_eta_rmse_of_empty_space_against_a_glass_ball():
    # eta = 1 everywhere against a ball of 1.5: the error is 0.5 on the ball's share of the
    # nodes, so RMSE = 0.5 sqrt(volume fraction) = 0.5 sqrt(4/3 pi 20^3 / 100^3)
    class Empty:
        def eta(self, pts):
            return np.ones(len(pts))

    want = 0.5 * math.sqrt(4 / 3 * math.pi * 20**3 / 100**3)
    got = eta_rmse_of(Empty(), Sphere(radius=20.0, eta=1.5, width=0.1), Box(), res=64)
    assert got == pytest.approx(want, rel=0.05)


def test_eval_of_the_truth_on_a_grid(sphere_data, tmp_path, monkeypatch):
    from test_metrics import _srgb, ssim_reference

    from clrefract import evaluate
    from clrefract.dataset import Dataset

    scored = []  # the (render, photograph) pairs the eval scored

    def recorded(a, b):
        scored.append((np.array(a), np.array(b)))
        return psnr_ssim(a, b)

    monkeypatch.setattr(evaluate, "psnr_ssim", recorded)
    run = _truth_run(tmp_path / "run", sphere_data)
    res = evaluate_run(run, views=2, samples=20000)
    assert len(res["views"]) == 2 and len(scored) == 2 and res["psnr"] > 15
    # each view's scores against the float64 references of the images it rendered, and the
    # test views' own photographs (measured off by 7e-9 in SSIM, 2e-6 dB in PSNR: float32
    # sRGB); the truth on a 32^3 grid scores SSIM 0.52 and 0.58 here
    ds = Dataset(sphere_data)
    for v, (img, ref), cam in zip(res["views"], scored, ds.test):
        assert np.array_equal(ref, ds.image(cam))
        assert v["ssim"] == pytest.approx(ssim_reference(img, ref), abs=5e-8)
        mse = np.mean((_srgb(img.astype(np.float64)) - _srgb(ref.astype(np.float64))) ** 2)
        assert v["psnr"] == pytest.approx(-10 * np.log10(mse), abs=2e-5)
    assert res["ssim"] == pytest.approx(np.mean([v["ssim"] for v in res["views"]]), abs=1e-12)
    assert 0.4 < res["ssim"] < 0.7
    assert res["chamfer_mm"] < 1.5  # a 32^3 grid (3.2 mm cells) of the exact ball
    assert res["eta_rmse"] < 0.05
    for name in ("eval.json", "eval.md", "slices.png", "surface.png", "views/r_000.png"):
        assert (run / "eval" / name).is_file(), name
    saved = json.loads((run / "eval" / "eval.json").read_text())
    assert saved["psnr"] == pytest.approx(res["psnr"])


def test_eval_without_ground_truth_scores_images_only(sphere_data, tmp_path, capsys):
    data = tmp_path / "capture"
    shutil.copytree(sphere_data, data)
    scene = json.loads((data / "scene.json").read_text())
    scene.pop("object")
    scene.pop("ground_truth")
    (data / "scene.json").write_text(json.dumps(scene))
    (data / "gt_surface.ply").unlink()
    run = _truth_run(tmp_path / "run", sphere_data)
    assert main(["eval", str(run), "--dataset", str(data), "--views", "1", "--no-figures"]) == 0
    out = capsys.readouterr().out
    assert "image metrics only" in out
    res = json.loads((run / "eval" / "eval.json").read_text())
    assert res["chamfer_mm"] is None and res["eta_rmse"] is None
    assert np.isfinite(res["psnr"])


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda p: None, "run folder not found"),
        (lambda p: p.mkdir(), "not a finished run"),
        (lambda p: (p.mkdir(), (p / "checkpoint.npz").write_bytes(b"x")), "unfinished run"),
    ],
)
def test_eval_of_a_broken_run_is_one_line(tmp_path, capsys, make, words):
    run = tmp_path / "run"
    make(run)
    assert main(["eval", str(run)]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1


def test_eval_of_an_older_run_without_run_json(sphere_data, tmp_path, capsys):
    """Runs made before run.json and config.toml: the dataset's box and the default step."""
    run = _truth_run(tmp_path / "run", sphere_data)
    (run / "run.json").unlink()
    assert main(["eval", str(run), "--views", "1"]) == 2  # which dataset? it must be told
    err = capsys.readouterr().err.strip()
    assert "--dataset" in err and len(err.splitlines()) == 1
    res = evaluate_run(run, sphere_data, views=1, figures=False, samples=5000)
    assert res["psnr"] > 15 and res["chamfer_mm"] < 1.5
    assert any("no config.toml" in n for n in res["notes"])
