"""`clrefract dataset register-env`: the panorama's rotation and each view's exposure and
white balance, recovered from the background pixels of scripted scenes rendered with a known
rotation and scaled by known gains."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from clrefract.calibrate import background_views, calibrate, rotation_angle, split_gain
from clrefract.cameras import load_transforms, save_transforms
from clrefract.cli import main
from clrefract.dataset import Dataset, box_of, read_frame_image
from clrefract.errors import ClrefractError
from clrefract.imageio import read_exr_rgb, write_exr_rgb
from clrefract.metrics import psnr_ssim
from clrefract.synth import MakeOptions, make_dataset

TURN = [5.0, -5.0, 5.0]  # degrees about x, y, z
BOX = "-22,-22,-22,22,22,22"  # holds the sphere (radius 20 mm), leaves the views' rims free


@pytest.fixture(scope="module")
def rotated(tmp_path_factory):
    """The sphere rendered with the panorama turned by TURN (the key then deleted), each
    frame divided by a known RGB gain: (folder, {file_path: gain})."""
    root = tmp_path_factory.mktemp("calibrate") / "turned"
    opt = MakeOptions(views=12, res=48, env_width=512, volume_res=16, env_rotation=TURN)
    make_dataset("sphere", root, opt)
    scene = json.loads((root / "scene.json").read_text())
    assert scene.pop("envmap_rotation") == TURN
    (root / "scene.json").write_text(json.dumps(scene))
    rng = np.random.default_rng(3)
    gains = {}
    for name in ("transforms_train.json", "transforms_test.json"):
        for cam in load_transforms(root / name):
            g = 2.0 ** rng.uniform(-0.3, 0.3) * rng.uniform(0.96, 1.04, 3)  # +-0.3 EV, tint
            path = root / f"{cam.file_path}.exr"
            write_exr_rgb(path, read_exr_rgb(path) / g)
            gains[cam.file_path] = g
    return root, gains


def test_rotation_and_gains_recovered_and_written(rotated, tmp_path, capsys):
    root = tmp_path / "d"
    shutil.copytree(rotated[0], root)
    before = json.loads((root / "scene.json").read_text())
    poses = json.loads((root / "transforms_train.json").read_text())
    rc = main(["-q", "dataset", "register-env", str(root), "--box", BOX, "--exposure", "--write"])
    assert rc == 0
    info = json.loads(capsys.readouterr().out)
    scene = json.loads((root / "scene.json").read_text())
    assert np.abs(np.subtract(scene["envmap_rotation"], TURN)).max() < 0.2
    assert rotation_angle(scene["envmap_rotation"], TURN) < 0.2
    assert info["residual_log_rms"] < 0.01 < info["residual_log_rms_before"]
    assert {k: v for k, v in scene.items() if k != "envmap_rotation"} == before
    cams = load_transforms(root / "transforms_train.json") + load_transforms(
        root / "transforms_test.json"
    )
    assert len(cams) == 12
    for cam in cams:
        found = cam.exposure * np.array(cam.white_balance)
        assert np.abs(found / rotated[1][cam.file_path] - 1).max() < 0.01, cam.file_path
        assert abs(np.prod(cam.white_balance) - 1) < 1e-4  # the tint alone, exposure apart
    after = json.loads((root / "transforms_train.json").read_text())
    for a, b in zip(after["frames"], poses["frames"], strict=True):
        assert a["transform_matrix"] == b["transform_matrix"]
    # read back as a fit reads them, the background pixels now match the rotated panorama
    ds = Dataset(root)
    env = ds.envmap()
    for v in background_views(ds, box_of(BOX))[:3]:
        assert np.abs(v.rgb / env.lookup(v.dirs) - 1).max() < 0.01
    # again from what was written, the rotation kept: nothing left to correct
    again = calibrate(root, exposure=True, box=box_of(BOX), keep_rotation=True)
    assert again["envmap_rotation"] == scene["envmap_rotation"]
    assert again["residual_log_rms"] == pytest.approx(info["residual_log_rms"], abs=1e-4)
    for f, cam in zip(again["frames"], cams, strict=True):
        assert f["exposure_scale"] == pytest.approx(cam.exposure, rel=1e-4)
        assert np.allclose(f["white_balance"], cam.white_balance, rtol=1e-4)


def test_default_box_uses_every_pixel_and_trims_the_object(rotated):
    # the default box (100 mm) fills every view: the object's refracted pixels are trimmed
    info = calibrate(rotated[0], exposure=True)
    assert info["pixels"].startswith("every pixel")
    assert rotation_angle(info["envmap_rotation"], TURN) < 0.2
    for f in info["frames"]:
        found = f["exposure_scale"] * np.array(f["white_balance"])
        assert np.abs(found / rotated[1][f["file_path"]] - 1).max() < 0.01, f["frame"]


def test_unrotated_panorama_gives_identity(sphere_25x48):
    # sphere_25x48 is read-only: without --write nothing may be written (the fixture checks)
    info = calibrate(sphere_25x48, exposure=True, box=box_of(BOX))
    assert np.abs(info["envmap_rotation"]).max() < 0.02
    assert info["residual_log_rms"] < 1e-3
    for f in info["frames"]:
        gain = f["exposure_scale"] * np.array(f["white_balance"])
        assert np.abs(gain - 1).max() < 1e-3, f["frame"]
    assert info["written"] == []


def test_white_balance_multiplies_after_exposure(sphere_8x24, tmp_path):
    cams = load_transforms(sphere_8x24 / "transforms_train.json")
    cams[0].exposure, cams[0].white_balance = 2.0, (1.1, 1.0, 0.9)
    save_transforms(tmp_path / "t.json", cams)
    back = load_transforms(tmp_path / "t.json")
    assert back[0].white_balance == (1.1, 1.0, 0.9) and back[0].exposure == 2.0
    assert back[1].white_balance == (1.0, 1.0, 1.0)
    path = sphere_8x24 / f"{cams[0].file_path}.exr"
    img, _, _ = read_frame_image(path, back[0])
    assert np.allclose(img, read_exr_rgb(path) * 2.0 * np.array([1.1, 1.0, 0.9]), rtol=1e-6)
    assert split_gain([2.2, 2.0, 1.8])[0] == pytest.approx((2.2 * 2.0 * 1.8) ** (1 / 3))


def test_top_level_white_balance_and_bad_values(sphere_8x24, tmp_path):
    top = json.loads((sphere_8x24 / "transforms_train.json").read_text())
    top["white_balance"] = [1.2, 1.0, 0.8]
    top["frames"][1]["white_balance"] = [1.0, 1.0, 1.05]
    (tmp_path / "t.json").write_text(json.dumps(top))
    cams = load_transforms(tmp_path / "t.json")
    assert cams[0].white_balance == (1.2, 1.0, 0.8)
    assert cams[1].white_balance == (1.0, 1.0, 1.05)
    for bad in ([1.0, 0.0, 1.0], [1.0, 1.0], "white", [1.0, True, 1.0]):
        top["frames"][1]["white_balance"] = bad
        (tmp_path / "t.json").write_text(json.dumps(top))
        with pytest.raises(ClrefractError, match=r"t\.json: frames\[1\]: 'white_balance'"):
            load_transforms(tmp_path / "t.json")


def _refused(capsys, argv, *words):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    for w in words:
        assert w in err, err


def test_bad_input_refused_in_one_line(sphere_8x24, tmp_path, capsys):
    root = tmp_path / "d"
    shutil.copytree(sphere_8x24, root)
    scene = root / "scene.json"
    text = scene.read_text()
    # a box that fills every view: no ray reaches the panorama past it
    argv = ["-q", "dataset", "register-env", str(root), "--box", "-50,-50,-50,50,50,50"]
    argv += ["--exposure", "--write"]
    _refused(capsys, argv, str(scene), "no background pixels", "--box")
    assert scene.read_text() == text
    frames = (root / "transforms_train.json").read_text()
    scene.write_text("{not json")
    _refused(capsys, argv, str(scene), "cannot read")
    assert (root / "transforms_train.json").read_text() == frames


def _turned_cameras(clean, root, degrees: float) -> list[np.ndarray]:
    """A copy of `clean` at `root` whose training cameras are each turned by `degrees` about
    a random axis; their true poses."""
    from clrefract.calibrate import rotvec_matrix

    shutil.copytree(clean, root)
    rng = np.random.default_rng(5)
    path = root / "transforms_train.json"
    d = json.loads(path.read_text())
    true = [np.array(f["transform_matrix"]) for f in d["frames"]]
    for f in d["frames"]:
        axis = rng.normal(size=3)
        turn = rotvec_matrix(np.radians(degrees) * axis / np.linalg.norm(axis))
        c2w = np.array(f["transform_matrix"])
        c2w[:3, :3] = turn @ c2w[:3, :3]
        f["transform_matrix"] = c2w.tolist()
    path.write_text(json.dumps(d))
    return true


def test_poses_turned_back_onto_the_panorama(sphere_25x48, tmp_path):
    # each recorded camera turned by 0.3 degrees (half a pixel at 48 x 48) about a random
    # axis; its background pixels turn it back, its position stays
    root = tmp_path / "d"
    true = _turned_cameras(sphere_25x48, root, 0.3)
    path = root / "transforms_train.json"
    info = calibrate(root, box=box_of(BOX), keep_rotation=True, poses=True, write=True)
    assert all(abs(t - 0.3) < 0.05 for t in info["view_turns_deg"][: len(true)])
    for cam, t in zip(load_transforms(path), true, strict=True):
        assert rotation_angle(np.eye(3), cam.c2w[:3, :3] @ t[:3, :3].T) < 0.03
        assert np.allclose(cam.c2w[:3, 3], t[:3, 3])


def test_frames_pair_each_camera_with_its_place_in_its_file(sphere_25x48, tmp_path):
    # two transforms files: each file's frames in order; one file split by holdout: its
    # frames in order, each the very camera `train` or `test` holds
    ds = Dataset(sphere_25x48)
    want = [
        (name, k, cam.file_path)
        for name in ("transforms_train.json", "transforms_test.json")
        for k, cam in enumerate(load_transforms(sphere_25x48 / name))
    ]
    assert [(s.name, k, c.file_path) for s, k, c in ds.frames()] == want
    root = tmp_path / "one"
    shutil.copytree(sphere_25x48, root)
    scene = json.loads((root / "scene.json").read_text())
    scene.update(test="transforms_train.json", holdout_every=4)
    (root / "scene.json").write_text(json.dumps(scene))
    ds = Dataset(root)
    frames = ds.frames()
    file = load_transforms(root / "transforms_train.json")
    assert [(k, c.file_path) for _, k, c in frames] == [
        (k, c.file_path) for k, c in enumerate(file)
    ]
    held = [c for _, k, c in frames if k % 4 == 0]
    assert len(held) == len(ds.test) and all(a is b for a, b in zip(held, ds.test, strict=True))
    assert sum(any(c is t for t in ds.train) for _, _, c in frames) == len(ds.train)


def test_corrections_in_memory_are_what_the_written_files_read(rotated, tmp_path):
    from clrefract.calibrate import Corrections, mismatch, register

    root = tmp_path / "d"
    shutil.copytree(rotated[0], root)
    assert mismatch(Dataset(root)).needs_registration()
    _, found = register(Dataset(root), exposure=True, poses=True)
    kept = Corrections.from_dict(json.loads(json.dumps(found.to_dict())), root)
    memory = Dataset(root)
    kept.apply(memory)
    found.write(root)
    disk = Dataset(root)
    assert rotation_angle(memory.scene.envmap_rotation, disk.scene.envmap_rotation) < 1e-6
    assert rotation_angle(disk.scene.envmap_rotation, TURN) < 0.2
    for (_, _, a), (_, _, b) in zip(memory.frames(), disk.frames(), strict=True):
        assert np.abs(a.c2w - b.c2w).max() < 1e-9
        assert a.exposure == pytest.approx(b.exposure, rel=1e-9)
        assert a.white_balance == pytest.approx(b.white_balance, rel=1e-9)
        found_gain = a.exposure * np.array(a.white_balance)
        assert np.abs(found_gain / rotated[1][a.file_path] - 1).max() < 0.01, a.file_path
    # registered, nothing is left to register
    assert not mismatch(memory).needs_registration()


def test_check_tells_a_dataset_that_needs_registering_from_a_clean_one(
    rotated, sphere_25x48, capsys, tmp_path
):
    from clrefract.calibrate import (
        MISMATCH_GAIN_LOG,
        MISMATCH_RESIDUAL,
        describe_background,
        mismatch,
    )

    turned = mismatch(Dataset(rotated[0]))
    assert turned.residual > 2 * MISMATCH_RESIDUAL and turned.gain_log > 2 * MISMATCH_GAIN_LOG
    clean = mismatch(Dataset(sphere_25x48))
    assert clean.residual < MISMATCH_RESIDUAL / 4 and clean.gain_log < MISMATCH_GAIN_LOG / 10
    assert clean.turn_deg < 0.005 and not clean.needs_registration()
    # the training cameras turned by 0.1 degree (a sixth of a pixel): to first order, each
    # view's background pixels give the turn (the test views' cameras are not turned)
    _turned_cameras(sphere_25x48, tmp_path / "t", 0.1)
    cams = mismatch(Dataset(tmp_path / "t"))
    assert cams.residual < MISMATCH_RESIDUAL and cams.gain_log < MISMATCH_GAIN_LOG
    assert 0.08 < cams.turn_deg < 0.12 and cams.needs_registration()
    notes: list[str] = []
    describe_background(rotated[0], None, notes)
    assert len(notes) == 1 and "register-env --exposure --poses --write" in notes[0], notes
    notes = []
    describe_background(sphere_25x48, None, notes)
    assert notes == []
    assert main(["dataset", "check", str(rotated[0])]) == 0  # a warning, not a problem
    out = capsys.readouterr().out
    assert "warning: the background differs from the panorama" in out and out.endswith("OK\n")


def test_a_fit_registers_what_its_dataset_needs_and_its_readers_apply_it(rotated, tmp_path):
    # the sphere with its panorama turned and its frames' gains unknown: the fit registers
    # both into its run folder, leaves the dataset's files as they are, and eval scores the
    # run's views as the fit did; told not to, it starts from the unregistered masks
    root = rotated[0]
    files = {p.name: p.read_bytes() for p in root.glob("*.json")}
    fit = ["fit", str(root), "--field-kind", "voxel", "--grid-res", "16", "--step", "2"]
    fit += ["--iterations", "4", "-q"]
    run = tmp_path / "run"
    assert main([*fit, "--out", str(run)]) == 0
    assert {p.name: p.read_bytes() for p in root.glob("*.json")} == files
    kept = json.loads((run / "registration.json").read_text())
    assert rotation_angle(kept["envmap_rotation"], TURN) < 0.2
    assert len(kept["frames"]) == 12
    for f in kept["frames"]:
        gain = f["exposure_scale"] * np.array(f["white_balance"])
        cam = load_transforms(root / f["file"])[f["index"]]
        assert np.abs(gain / rotated[1][cam.file_path] - 1).max() < 0.01
    # the run's own dataset is read registered (eval, report, render, refine-positions);
    # another is read as it states itself
    from clrefract.evaluate import run_dataset

    own = run_dataset(run, None)
    assert rotation_angle(own.scene.envmap_rotation, kept["envmap_rotation"]) < 1e-9
    shutil.copytree(root, tmp_path / "copy")
    assert run_dataset(run, tmp_path / "copy").scene.envmap_rotation is None
    # render shows the run's first test view as the photograph, registered, shows it
    photo = own.image(own.test[0])
    scores = []
    for data, out in ((root, "render-own"), (tmp_path / "copy", "render-copy")):
        argv = ["-q", "render", "--field", str(run), "--dataset", str(data), "--only", "0"]
        assert main([*argv, "--step", "2", "--out", str(tmp_path / out)]) == 0
        scores.append(psnr_ssim(read_exr_rgb(next((tmp_path / out).glob("*.exr"))), photo)[0])
    assert scores[0] > scores[1] + 3, scores
    page = (run / "report.html").read_text()  # what it found, beside the scores
    assert "<h2>Registration</h2>" in page and "registration figure failed" not in page
    # a real capture's camera centres are fitted with the field (camera_centres = "auto")
    assert 'camera_centres = "fitted"' in (run / "config.toml").read_text()
    moved = json.loads((run / "camera_centres.json").read_text())["views"]
    from clrefract.dataset import Dataset
    from clrefract.fit.config import FitConfig
    from clrefract.fit.rays import held_out_views

    n_train = len(Dataset(root).train)  # less the held-out views, which keep their centres
    assert len(moved) == n_train - len(held_out_views(FitConfig(), n_train)) > 0
    # (after 4 steps none has moved: no centre moves before it has a spread to test against)
    assert "<h2>Camera centres</h2>" in page and "camera centres figure failed" not in page
    results = json.loads((run / "results.json").read_text())
    assert main(["-q", "eval", str(run), "--out", str(tmp_path / "eval")]) == 0
    scored = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert scored["psnr"] == pytest.approx(results["test_psnr"], abs=0.01)
    off = tmp_path / "off"
    assert main([*fit, "--out", str(off), "--register", "off"]) == 0
    assert not (off / "registration.json").exists()
    assert 'camera_centres = "recorded"' in (off / "config.toml").read_text()
    assert not (off / "camera_centres.json").exists()
    unregistered = json.loads((off / "results.json").read_text())["test_psnr"]
    assert results["test_psnr"] > unregistered + 3, (results["test_psnr"], unregistered)


def test_a_fit_whose_views_hold_no_background_goes_on_as_stated(sphere_8x24, tmp_path, capsys):
    # a box that fills every view leaves no pixel that sees the panorama straight
    fit = ["fit", str(sphere_8x24), "--box", "-50,-50,-50,50,50,50", "--field-kind", "voxel"]
    fit += ["--iterations", "2", "--grid-res", "8", "--step", "4", "--test-views", "1"]
    assert main([*fit, "--out", str(tmp_path / "auto")]) == 0
    err = capsys.readouterr().err
    assert "register: not checked" in err and "no background pixels" in err
    assert not (tmp_path / "auto" / "registration.json").exists()
    # told to register, it cannot: one line, status 2, and no run left behind
    _refused(capsys, [*fit, "--out", str(tmp_path / "on"), "--register", "on"], "no background")
    assert not (tmp_path / "on").exists()
