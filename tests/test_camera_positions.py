"""`clrefract dataset refine-positions`: camera centres recorded a known distance off the true
ones (realistic.py's pose flaw), moved back by fitting renders of the true sphere."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from clrefract.cameras import load_transforms
from clrefract.cli import main
from clrefract.dataset import Dataset
from clrefract.fields.interface import InterfaceField, SphereInterface
from clrefract.interface import InterfaceTracer
from clrefract.realistic import TRUTH_FILE, parse_flaws
from clrefract.synth import MakeOptions, make_dataset
from clrefract.view_offsets import BLUR_PX, MAX_NFEV, PROGRESS_PER_VIEW, estimate_offsets

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
    tracer = InterfaceTracer(field, ds.box)
    launches = []
    trace = tracer.trace
    tracer.trace = lambda o, d: launches.append(len(o)) or trace(o, d)
    counts = []
    offsets = estimate_offsets(ds, tracer, progress=lambda n=1: counts.append(n))
    assert sum(counts) == len(ds.train) * PROGRESS_PER_VIEW  # the bar ends full
    # the views step together: one launch for every view's bent pixels, then each round's
    # first residuals and its iterations' two launches (view by view: 20 x 55 or so)
    assert len(launches) <= 1 + len(BLUR_PX) * (1 + 2 * MAX_NFEV), launches
    assert launches[0] == sum(cam.width * cam.height for cam in ds.train)
    truth = true_positions(moved)
    before = in_plane_errors(ds.train, truth)
    after = in_plane_errors(ds.train, truth, [v.offset_mm for v in offsets])
    assert rms(before) > 0.5 * POSE_MM  # two of three directions of a random shift
    assert rms(after) < 0.1 * rms(before), (rms(before), rms(after))
    assert all(v.loss_after < v.loss_before for v in offsets)
    for v, cam in zip(offsets, ds.train, strict=True):  # in the image plane only
        assert abs(v.offset_mm @ cam.c2w[:3, 2]) < 1e-9


def test_on_jpeg_frames_colour_is_compared_per_block_as_stored(tmp_path):
    """4:2:0 JPEG frames: solved in the fit's srgb420 (luma per pixel, colour per 2 x 2 block
    as the file stored it), the cameras come back closer than per pixel against the decoded
    frames, whose smeared colour edges pull each view (measured: 0.038 mm and 0.091 mm left
    of 0.79)."""
    opt = MakeOptions(views=20, res=48, env_width=512, volume_res=16)
    opt.realistic = parse_flaws(f"pose_mm={POSE_MM},jpeg=90")
    make_dataset("sphere", tmp_path / "jpeg", opt)
    truth = true_positions(tmp_path / "jpeg")
    left = {}
    for chroma, space in (("decoded", "srgb"), ("stored", "srgb420")):
        ds = Dataset(tmp_path / "jpeg")
        ds.train_chroma = chroma
        field = SphereInterface((0.0, 0.0, 0.0), 20.0, 1.5, ds.box)
        offsets = estimate_offsets(ds, InterfaceTracer(field, ds.box), space=space)
        before = in_plane_errors(ds.train, truth)
        left[space] = rms(in_plane_errors(ds.train, truth, [v.offset_mm for v in offsets]))
    assert left["srgb420"] < 0.1 * rms(before), (rms(before), left)
    assert left["srgb420"] < 0.6 * left["srgb"], left


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


# --- camera centres fitted with the field (fit/centres.py) ------------------------------------
def less_common(err: np.ndarray, cams) -> np.ndarray:
    """In-plane errors (n, 2) less the common world translation that fits them best: the part
    a fit of camera centres leaves to the object's position."""
    b = np.stack([cam.c2w[:3, :2] for cam in cams])
    t = np.linalg.solve(np.einsum("vkj,vlj->kl", b, b), np.einsum("vkj,vj->k", b, err))
    return err - np.einsum("vkj,k->vj", b, t)


def test_the_centres_move_back_against_the_true_sphere(moved):
    """Only the centres move (the true sphere held): the summed origin gradients of each
    view's rays, their rate decaying as a fit's, take the in-plane errors, less their common
    part, below half (measured: 0.31 of them; a tenth of a pixel is left, where the
    silhouette's rays, which carry no gradient, would tell more)."""
    from clrefract.fit.centres import CameraCentres
    from clrefract.fit.config import FitConfig
    from clrefract.fit.objective import Objective
    from clrefract.fit.rays import TrainingRays, batch_indices
    from clrefract.interface import InterfaceEngine
    from clrefract.resolution import pixel_footprint_mm

    ds = Dataset(moved)
    cfg = FitConfig(val_views=0, batch=4096)
    rays = TrainingRays(ds, cfg)
    steps = 150
    centres = CameraCentres(
        ds.train, rays.view_of, rays.held, pixel_footprint_mm(ds.train, (0, 0, 0)), lr=0.02,
        decay=lambda it: 0.1 ** (it / steps),
    )  # fmt: skip
    objective = Objective(rays, "srgb", cfg.batch, cfg.seed, centres)
    engine = InterfaceEngine(SphereInterface((0.0, 0.0, 0.0), 20.0, 1.5, ds.box), ds.box)
    truth = true_positions(moved)
    before = less_common(in_plane_errors(ds.train, truth), ds.train)
    first = objective.loss_and_grad(engine, batch_indices(cfg, 0, rays.pool), step=0).loss
    for it in range(1, steps):
        last = objective.loss_and_grad(engine, batch_indices(cfg, it, rays.pool), step=it).loss
    after = less_common(in_plane_errors(ds.train, truth, centres.world()), ds.train)
    assert rms(before) > 0.5 * POSE_MM
    assert rms(after) < 0.45 * rms(before), (rms(before), rms(after))
    assert last < 0.5 * first, (first, last)
    # in the image plane only, and no common translation left
    for off, cam in zip(centres.world(), ds.train, strict=True):
        assert abs(off @ cam.c2w[:3, 2]) < 1e-9
    np.testing.assert_allclose(less_common(centres.uv, ds.train), centres.uv, atol=1e-12)


def test_a_fit_of_centres_writes_them_and_resumes_as_if_uninterrupted(
    moved, tmp_path, capsys, monkeypatch
):
    """`fit --camera-centres fitted`: camera_centres.json names each training view's move,
    which takes the in-plane errors (less their common part) below half of the recorded
    ones in 24 steps on a 24^3 grid (measured: 0.32; the solves after steps 6 and 12 moved
    the centres by 0.79 mm and 0.1 mm, rms). A run interrupted between its solves resumes
    with the centres and their moments as the checkpoint holds them, and solves once more:
    the solve it had done is not repeated, the one it had not is not skipped."""
    import clrefract.fit as fitmod
    from clrefract.fit.centres import CameraCentres

    def fit(run, *more):
        args = ["fit", str(moved), "--out", str(run), "--field-kind", "interface", "--quiet"]
        args += ["--camera-centres", "fitted", "--lr-centres", "0.05", "--grid-res", "24"]
        return main([*args, "--iterations", "24", *more])

    solved = []
    real_take = CameraCentres.take_solved

    def take_solved(self, views, right_up):
        solved.append(np.array(right_up))
        return real_take(self, views, right_up)

    monkeypatch.setattr(CameraCentres, "take_solved", take_solved)
    assert fit(tmp_path / "full") == 0
    assert len(solved) == 2  # after steps 6 and 12 of 24
    assert rms(solved[0]) > 0.1, rms(solved[0])  # mm: the first moves them
    real_step = fitmod.Fit.step

    def step_then_interrupt(self):
        if self.it == 8:
            import os
            import signal

            os.kill(os.getpid(), signal.SIGINT)
        return real_step(self)

    monkeypatch.setattr(fitmod.Fit, "step", step_then_interrupt)
    solved.clear()
    assert fit(tmp_path / "part") == 2
    assert "interrupted at iteration 9" in capsys.readouterr().err
    assert len(solved) == 1
    saved = dict(np.load(tmp_path / "part" / "checkpoint.npz"))
    resumed = {}

    def first_step_records(self):
        if not resumed:
            resumed.update({k: np.copy(v) for k, v in self.objective.centres.state().items()})
            resumed["at"] = self.it
        return real_step(self)

    monkeypatch.setattr(fitmod.Fit, "step", first_step_records)
    solved.clear()
    assert fit(tmp_path / "part", "--resume") == 0
    capsys.readouterr()
    assert len(solved) == 1  # after step 12 only
    assert resumed.pop("at") == 9
    for key, value in resumed.items():
        np.testing.assert_array_equal(value, saved[key], err_msg=key)
    assert np.abs(saved["centres_uv"]).max() > 0.05  # mm: the first 9 steps moved them
    part = np.load(tmp_path / "part" / "checkpoint.npz")["centres_uv"]
    assert np.abs(part - saved["centres_uv"]).max() > 0.01  # and the last 15 too
    doc = json.loads((tmp_path / "full" / "camera_centres.json").read_text())
    assert 0 < len(doc["views"]) < len(Dataset(moved).train)  # held-out views keep theirs
    full = np.load(tmp_path / "full" / "checkpoint.npz")["centres_uv"]
    uv = np.array([v["right_up_mm"] for v in doc["views"]])
    np.testing.assert_allclose(uv, full[np.any(full != 0, axis=1)], atol=1e-4)  # rounded
    assert all(v["frame"].startswith("transforms_train.json: frames[") for v in doc["views"])
    ds = Dataset(moved)
    names = {v["file_path"]: np.array(v["offset_mm"]) for v in doc["views"]}
    cams = [cam for cam in ds.train if cam.file_path in names]
    truth = true_positions(moved)
    before = less_common(in_plane_errors(cams, truth), cams)
    after = less_common(in_plane_errors(cams, truth, [names[c.file_path] for c in cams]), cams)
    assert rms(after) < 0.45 * rms(before), (rms(before), rms(after))


def test_bad_rates_of_centres_are_refused(moved, tmp_path, capsys):
    argv = ["fit", str(moved), "--out", str(tmp_path / "run"), "--camera-centres", "fitted"]
    assert main([*argv, "--lr-centres", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "lr_centres" in err, err
    assert not (tmp_path / "run").exists()


def test_a_centre_moves_where_its_gradient_stands_out_of_its_noise():
    """The step rule alone, on made-up gradients: pure noise leaves a centre where it is
    (Adam would walk it off by its rate at every step), a pull in as much noise moves it, a
    steady one not before MIN_SEEN steps have been seen, and one that flips sign stops it."""
    from types import SimpleNamespace

    from clrefract.fit.centres import MIN_SEEN, CameraCentres

    rng = np.random.default_rng(0)
    turns = [np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(12)]
    cams = [SimpleNamespace(c2w=np.block([[t, np.zeros((3, 1))], [0, 0, 0, 1]])) for t in turns]
    view_of = np.repeat(np.arange(12), 10)
    rays = np.arange(120)

    def centres():
        return CameraCentres(cams, view_of, np.array([], int), footprint=1.0, lr=0.01)

    still = centres()  # noise alone: chance moves at most (Adam: its rate at every step)
    for it in range(300):
        still.step(rays, rng.normal(size=(120, 3)), it)
    assert np.linalg.norm(still.uv, axis=1).max() < 0.1, still.uv  # of 3 mm for Adam
    # each view pulled along one of its own axes, in as much noise: it moves against its pull
    axes = rng.integers(0, 2, 12)
    pull = np.array([cams[v].c2w[:3, axes[v]] for v in view_of])
    fitted = centres()
    for it in range(300):
        fitted.step(rays, rng.normal(size=(120, 3)) + 0.5 * pull, it)
    along = fitted.uv[np.arange(12), axes]
    # a third of 300 steps of 0.01 mm at least (the common part taken out adds its share)
    assert np.all(along < -1.0), along
    steady = centres()
    for it in range(MIN_SEEN - 1):
        steady.step(rays, pull, it)
        assert not steady.uv.any()  # nothing to test a spread against yet
    flips = centres()
    for it in range(300):
        flips.step(rays, pull * (-1) ** it, it)
    assert np.abs(flips.uv).max() < 0.02


def test_auto_fits_the_centres_of_real_captures_alone(moved):
    """`camera_centres = "auto"`: fitted where the fit registered the capture or `dataset
    import` made it, recorded for a rendered dataset; a setting given stays."""
    from dataclasses import replace

    from clrefract.fit.centres import centres_setting
    from clrefract.fit.config import FitConfig

    scene = Dataset(moved).scene
    imported = replace(scene, extra={**scene.extra, "import": {"layout": "colmap"}})
    auto = FitConfig()
    assert auto.camera_centres == "auto"
    assert centres_setting(auto, scene, registered=False) == "recorded"
    assert centres_setting(auto, scene, registered=True) == "fitted"
    assert centres_setting(auto, imported, registered=False) == "fitted"
    for given in ("recorded", "fitted"):
        cfg = FitConfig(camera_centres=given)
        assert centres_setting(cfg, imported, registered=True) == given


def test_views_are_traced_together_in_launches_of_whole_views(moved, monkeypatch):
    """bent_pixels traces whole views together, up to LAUNCH_RAYS rays a launch: with room
    for two views of 48 x 48 a launch, 16 training views take 8 launches and bend the same pixels
    as one view at a time (the sphere's outline in each: some, never all)."""
    from clrefract import view_offsets

    ds = Dataset(moved)
    tracer = InterfaceTracer(SphereInterface((0.0, 0.0, 0.0), 20.0, 1.5, ds.box), ds.box)
    alone = [view_offsets.bent_pixels(tracer, [cam])[0] for cam in ds.train]
    launches = []
    trace = tracer.trace
    tracer.trace = lambda o, d: launches.append(len(o)) or trace(o, d)
    monkeypatch.setattr(view_offsets, "LAUNCH_RAYS", 2 * 48 * 48 + 1)
    together = view_offsets.bent_pixels(tracer, ds.train)
    assert len(ds.train) == 16 and launches == [2 * 48 * 48] * 8
    for a, b in zip(alone, together, strict=True):
        assert a.shape == (48, 48) and 0 < a.sum() < a.size
        assert np.array_equal(a, b)
