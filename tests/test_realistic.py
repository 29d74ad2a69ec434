"""`clrefract dataset make --realistic`: what the flawed capture records, and what it hides."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json

import numpy as np
import pytest

from clrefract.cli import main
from clrefract.dataset import Dataset, check_dataset
from clrefract.envmap import EnvMap, rotation_matrix
from clrefract.realistic import Flaws, load_truth, parse_flaws, pose_error
from clrefract.synth import MakeOptions, surface_mesh

SMALL = {"views": 8, "res": 48, "env_width": 512, "volume_res": 8}
LENS_ONLY = "k1=-0.05,k2=0.01,p1=0.001,p2=0.001"


def make_dataset(name, root, opt):
    """synth.make_dataset with a coarse ground-truth surface (2 mm, not 0.4 mm: a quarter of
    a second, not three), which no test here looks at."""
    from clrefract import synth

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(synth, "surface_mesh", functools.partial(surface_mesh, spacing=2.0))
        return synth.make_dataset(name, root, opt)


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    root = tmp_path_factory.mktemp("realistic") / "sphere"
    make_dataset("sphere", root, MakeOptions(**SMALL, realistic=Flaws()))
    return root


@pytest.fixture(scope="module")
def lens_only(tmp_path_factory):
    """The lens alone: linear EXR frames, no noise, true poses, no turn of the panorama."""
    root = tmp_path_factory.mktemp("lens") / "sphere"
    make_dataset("sphere", root, MakeOptions(**SMALL, realistic=parse_flaws(LENS_ONLY)))
    return root


def true_camera(cam, truth):
    frame = next(f for f in truth["frames"] if f["file_path"] == cam.file_path)
    return dataclasses.replace(cam, c2w=np.array(frame["transform_matrix"])), frame


def background(cam, rays_d, rays_o, clearance=23.0):
    """Pixels whose ray passes more than `clearance` mm from the sphere's centre (radius 20)."""
    along = -(rays_o * rays_d).sum(axis=1)
    return np.linalg.norm(rays_o + along[:, None] * rays_d, axis=1) > clearance


def test_records_lens_and_nominal_exposure_only(real):
    truth = load_truth(real)
    ds = Dataset(real)
    cams = ds.train + ds.test
    assert len(cams) == 8 and all(c.file_path.endswith(".jpg") for c in cams)
    for cam in cams:
        assert cam.camera_model == "OPENCV"
        assert cam.distortion == {"k1": -0.05, "k2": 0.01, "p1": 0.001, "p2": 0.001}
        # one nominal exposure for all: the per-view jitter is not recorded
        assert cam.exposure == pytest.approx(1 / truth["nominal_exposure"], rel=1e-12)
    scene = json.loads((real / "scene.json").read_text())
    assert "envmap_rotation" not in scene
    for name in ("transforms_train.json", "transforms_test.json"):
        text = (real / name).read_text()
        assert "white_balance" not in text and "gains" not in text
    # the truth: the panorama's turn as scene.json would give it
    assert truth["envmap_rotation"] == pytest.approx([3.0, -2.0, 4.0], abs=1e-9)
    gains = np.array([f["gains"] for f in truth["frames"]])
    assert np.all(np.abs(np.log2(gains[:, 1])) <= 0.3) and np.ptp(gains[:, 1]) > 0.1


def test_background_is_turned_panorama_through_lens_times_gains(real):
    """A background pixel as the loader reads it is the turned panorama seen along the true
    pose's distorted ray, times the view's gains: within 5% (median), the sensor's noise
    (1.6% at mid-grey) and the JPEG's (quality 90, 4:2:0 chroma, on a 48-pixel image of a
    busy panorama); a least-squares gain per view within 2.5% of the truth (the gains span
    +-23%). The panorama unturned misses by five times as much."""
    truth = load_truth(real)
    ds = Dataset(real)
    env = ds.envmap()
    turn = rotation_matrix([3.0, -2.0, 4.0])  # the stated default
    np.testing.assert_allclose(truth["envmap_rotation_matrix"], turn, atol=1e-12)
    turned = EnvMap(env.image, turn)
    for cam in ds.train + ds.test:
        cam_true, frame = true_camera(cam, truth)
        o, d = cam_true.rays()
        img, weight = ds.frame(cam)
        keep = background(cam, d, o) & (weight.ravel() > 0)
        assert keep.sum() > 1500
        seen = img.reshape(-1, 3)[keep].astype(np.float64)
        straight = turned.lookup(d[keep]).astype(np.float64)
        expect = straight * np.array(frame["gains"])
        rel = np.abs(seen - expect) / expect
        assert np.median(rel) < 0.05, (cam.file_path, np.median(rel))
        fitted = (seen * straight).sum(0) / (straight * straight).sum(0)
        np.testing.assert_allclose(fitted, frame["gains"], rtol=0.025)
        unturned = env.lookup(d[keep]) * np.array(frame["gains"])
        assert np.median(np.abs(seen - unturned) / unturned) > 5 * np.median(rel)


def test_recorded_poses_are_off_by_the_stated_amount(real):
    truth = load_truth(real)
    ds = Dataset(real)
    for cam in ds.train + ds.test:
        cam_true, frame = true_camera(cam, truth)
        np.testing.assert_array_equal(cam.c2w, frame["recorded_transform_matrix"])
        deg, mm = pose_error(cam_true.c2w, cam.c2w)
        assert deg == pytest.approx(0.1, abs=1e-9) and mm == pytest.approx(0.2, abs=1e-9)


def test_dataset_check_accepts_it(real, capsys):
    assert check_dataset(real) == []
    assert main(["dataset", "check", str(real)]) == 0
    assert capsys.readouterr().out.strip().endswith("OK")


def digest(root) -> str:
    h = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def test_seed_reproduces_the_dataset(tmp_path):
    tiny = {"views": 3, "res": 16, "env_width": 128, "volume_res": 4}
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        make_dataset("sphere", tmp_path / name, MakeOptions(**tiny, seed=seed, realistic=Flaws()))
    assert digest(tmp_path / "a") == digest(tmp_path / "b")
    a, c = load_truth(tmp_path / "a"), load_truth(tmp_path / "c")
    assert a["frames"][0]["gains"] != c["frames"][0]["gains"]
    first = [(tmp_path / k / "test/r_000.jpg").read_bytes() for k in "ac"]
    assert first[0] != first[1]


def test_a_pinhole_loader_misplaces_the_corners(lens_only):
    """Without the lens the corner pixels land 0.27 pixel off (OpenCV's model, by hand), and
    the noise-free frames there disagree with the panorama by more than 1% (RMS); through
    the recorded lens they agree to float rounding."""
    ds = Dataset(lens_only)
    env = ds.envmap()
    cam = ds.train[0]
    assert cam.exposure == 1.0 and cam.file_path.endswith(".exr")
    x = y = (0.5 - cam.cx) / cam.fl_x  # the top-left pixel's centre, normalised
    r2 = x * x + y * y
    radial = 1 - 0.05 * r2 + 0.01 * r2 * r2
    xd = x * radial + 2 * 0.001 * x * y + 0.001 * (r2 + 2 * x * x)
    yd = y * radial + 0.001 * (r2 + 2 * y * y) + 2 * 0.001 * x * y
    off = cam.fl_x * np.hypot(xd - x, yd - y)
    assert off == pytest.approx(
        cam.fl_x * np.hypot(*(np.array(cam.distort(x, y)) - (x, y))), rel=1e-9
    )
    assert 0.25 < off < 0.3
    img = ds.frame(cam)[0]
    corner = np.zeros(img.shape[:2], bool)
    for rows in (slice(0, 8), slice(-8, None)):
        for cols in (slice(0, 8), slice(-8, None)):
            corner[rows, cols] = True
    seen = img[corner].astype(np.float64)
    pinhole = dataclasses.replace(cam, camera_model="PINHOLE", distortion={})
    for c, worst in ((cam, 1e-5), (pinhole, None)):
        d = c.rays()[1].reshape(*img.shape[:2], 3)[corner]
        rms = np.sqrt(np.mean(((env.lookup(d) - seen) / seen) ** 2))
        if worst is not None:
            assert rms < worst
        else:
            assert rms > 0.01


@pytest.mark.parametrize(
    "flaws, words",
    [
        ("jpeg=high", "jpeg must be a number"),
        ("k9=1", "not KEY=VALUE"),
        ("k1=-3", "folds"),
        ("chroma=411", "chroma must be"),
    ],
)
def test_bad_flaws_are_refused_before_writing(tmp_path, capsys, flaws, words):
    out = tmp_path / "d"
    args = ["dataset", "make", "sphere", "--out", str(out), "--views", "2", "--res", "8"]
    assert main([*args, "--realistic", "--flaws", flaws]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not out.exists()


def test_jpeg_frames_with_halved_chroma_choose_the_420_loss(real, lens_only, tmp_path):
    """The loss follows the frames: 4:2:0 JPEGs (the realistic capture's, as phones write
    them) get srgb420, whose rays come in the aligned 2 x 2 blocks of the chroma samples; EXR
    frames keep srgb. The fit's config (what config.toml records) holds the choice, and its
    training frames' colour is what their blocks stored (imageio.stored_chroma)."""
    import io

    from clrefract.fit.config import FitConfig
    from clrefract.fit.rays import TrainingRays
    from clrefract.fit.trainer import Fit

    assert Dataset(real).chroma_halved() and not Dataset(lens_only).chroma_halved()
    rays = TrainingRays(Dataset(real), FitConfig())
    anchors = np.random.default_rng(0).choice(len(rays.rgb), 400, replace=False)
    idx = rays.chroma_blocks(anchors).reshape(100, 4)
    view = rays.view_of[idx]
    local = idx - rays.view_start[view]
    w = rays.view_shape[view[:, 0], 1]
    rows, cols = local // w[:, None], local % w[:, None]
    assert np.all(view == view[:, :1]) and np.all((idx == anchors[:100, None]).any(1))
    assert np.all(rows.min(1) % 2 == 0) and np.all(rows.max(1) == rows.min(1) + 1)
    assert np.all(cols.min(1) % 2 == 0) and np.all(cols.max(1) == cols.min(1) + 1)

    for data, want in ((real, "srgb420"), (lens_only, "srgb")):
        log = io.StringIO()
        fit = Fit(data, tmp_path / want, FitConfig(field="voxel", res=8), stream=log)
        assert fit.cfg.loss == want and ("loss: srgb420" in log.getvalue()) == (want == "srgb420")
        # training frames as their blocks stored their colour; test frames as decoded
        plain = Dataset(data)
        for split, changed in (("train", want == "srgb420"), ("test", False)):
            cam, same = getattr(fit.ds, split)[0], getattr(plain, split)[0]
            moved = np.abs(fit.ds.image(cam) - plain.image(same)).max()
            assert (moved > 1e-3) == changed, (split, moved)


def test_a_step_names_the_rays_its_radiance_is_of(real, tmp_path):
    """Under srgb420 a step compares the 2 x 2 blocks that hold its rays' first quarter, not
    the rays it was given: its result names them, so the step's PSNR is of those pixels (it
    was taken against the rays given: 13.0 dB where the blocks' is 16.0 on this capture)."""
    import io

    from clrefract.fit.config import FitConfig
    from clrefract.fit.trainer import Fit

    fit = Fit(real, tmp_path / "run", FitConfig(field="voxel", res=8), stream=io.StringIO())
    fit.bind(fit.make_field(8))
    idx = np.random.default_rng(0).choice(fit.rays.pool, 64, replace=False)
    res = fit.objective.loss_and_grad(fit.bound.engine, idx)
    assert fit.cfg.loss == "srgb420" and np.isin(idx[:16], res.rays).all()
    traced = fit.bound.tracer.trace(fit.rays.origins[res.rays], fit.rays.dirs[res.rays])
    np.testing.assert_allclose(fit.rays.env.lookup(traced.direction), res.radiance, atol=1e-5)
    given = fit.bound.tracer.trace(fit.rays.origins[idx], fit.rays.dirs[idx])
    assert np.abs(fit.rays.env.lookup(given.direction) - res.radiance).max() > 0.1
