"""Lens models of transforms.json (OPENCV, FULL_OPENCV, OPENCV_FISHEYE): rays through the
lens agree with OpenCV's projection of them; bad models and folding lenses are refused."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from clrefract.cameras import Camera, load_transforms, look_at, save_transforms
from clrefract.cli import main
from clrefract.hull import project

cv2 = pytest.importorskip("cv2", reason="OpenCV, the oracle, is the test extra's")

LENSES = {
    "OPENCV": dict(k1=-0.2, k2=0.05, p1=1e-3, p2=-5e-4),
    "FULL_OPENCV": dict(k1=-0.15, k2=0.03, k3=0.002, k4=0.05, k5=0.01, k6=0.001, p1=1e-3, p2=-5e-4),
    "OPENCV_FISHEYE": dict(k1=0.05, k2=-0.01, k3=0.003, k4=-0.001),
}


def _camera(model, dist, width=160, height=120):
    # wide (about 90 degrees across the diagonal) and off-centre
    return Camera(
        width,
        height,
        95.0,
        97.0,
        81.3,
        58.7,
        look_at([100.0, 50.0, 30.0]),
        camera_model=model,
        distortion=dist,
    )


def _opencv_pixels(cam, dirs):
    """OpenCV's projection of world directions (n, 3) into the camera's pixels (n, 2)."""
    dc = dirs @ cam.c2w[:3, :3]  # camera axes, OpenGL: looks down -z, y up
    pts = np.ascontiguousarray(np.stack([dc[:, 0], -dc[:, 1], -dc[:, 2]], axis=-1))
    k = np.array([[cam.fl_x, 0, cam.cx], [0, cam.fl_y, cam.cy], [0, 0, 1]])
    d = cam.distortion
    if cam.camera_model == "OPENCV_FISHEYE":
        coeffs = np.array([d.get(n, 0.0) for n in ("k1", "k2", "k3", "k4")])
        uv, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), k, coeffs)
    else:
        names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
        coeffs = np.array([d.get(n, 0.0) for n in names])
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), k, coeffs)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("model", sorted(LENSES))
def test_rays_agree_with_opencv_over_the_whole_image(model):
    cam = _camera(model, LENSES[model])
    o, d = cam.rays()
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    err = np.hypot(*(_opencv_pixels(cam, d) - np.stack([j.ravel(), i.ravel()], -1)).T)
    assert err.max() < 0.05, err.max()  # corners included
    # and the lens bends the corner rays by many pixels, so the test tests something
    bare = Camera(cam.width, cam.height, cam.fl_x, cam.fl_y, cam.cx, cam.cy, cam.c2w)
    assert np.degrees(np.arccos(np.clip((d * bare.rays()[1]).sum(1), -1, 1))).max() > 1.0
    # the hull's projection of points along the rays comes back to the pixel centres
    row, col, depth = project(cam, o + 300.0 * d)
    assert np.hypot(col - j.ravel(), row - i.ravel()).max() < 0.05


def test_pinhole_rays_are_unchanged():
    plain = Camera(9, 7, 11.0, 12.0, 4.25, 3.5, look_at([10.0, -20.0, 5.0]))
    for model in ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV"):
        other = Camera(9, 7, 11.0, 12.0, 4.25, 3.5, plain.c2w, camera_model=model)
        assert np.array_equal(other.rays()[1], plain.rays()[1])


def _frame(name="a.png", **extra):
    return {"file_path": name, "transform_matrix": look_at([0.0, -200.0, 0.0]).tolist(), **extra}


def test_transforms_models_load_and_round_trip(tmp_path):
    top = {"fl_x": 95.0, "fl_y": 97.0, "cx": 81.3, "cy": 58.7, "w": 160, "h": 120}
    frames = [
        _frame("a.png", camera_model="OPENCV", **LENSES["OPENCV"]),
        _frame("b.png", camera_model="opencv_fisheye", **LENSES["OPENCV_FISHEYE"]),
        _frame("c.png"),
        _frame("d.png", k1=-0.1),  # instant-ngp: coefficients without a model are OpenCV's
    ]
    path = tmp_path / "transforms.json"
    path.write_text(
        json.dumps({**top, "camera_model": "FULL_OPENCV", "k4": 0.01, "frames": frames})
    )
    cams = load_transforms(path)
    assert [c.camera_model for c in cams] == [
        "OPENCV",
        "OPENCV_FISHEYE",
        "FULL_OPENCV",
        "FULL_OPENCV",
    ]
    assert cams[2].distortion == {"k4": 0.01}
    assert cams[3].distortion == {"k1": -0.1, "k4": 0.01}
    out = tmp_path / "saved.json"
    for order in (
        cams,
        cams[::-1],
        [Camera(160, 120, 95.0, 97.0, 81.3, 58.7, cams[0].c2w, file_path="p.png"), *cams],
    ):
        save_transforms(out, order)
        back = load_transforms(out)
        assert [(c.camera_model, c.distortion) for c in back] == [
            (c.camera_model, c.distortion) for c in order
        ]
        assert all(np.array_equal(a.rays()[1], b.rays()[1]) for a, b in zip(order, back))


def _check_refuses(ds, tmp_path, capsys, edit, *needles):
    root = tmp_path / "ds"
    shutil.copytree(ds, root)
    tf = root / "transforms_train.json"
    d = json.loads(tf.read_text())
    edit(d)
    tf.write_text(json.dumps(d))
    code = main(["dataset", "check", str(root)])
    out, err = capsys.readouterr()
    # dataset check lists each problem in one line and exits 2
    lines = [ln for ln in out.splitlines() if "transforms_train.json" in ln]
    assert code == 2, out + err
    assert len(lines) == 1 and "Traceback" not in out + err, out + err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    # fit refuses it in one error line, before any work
    code = main(["fit", str(root), "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("clrefract: error:")]
    assert code == 2 and len(lines) == 1 and "transforms_train.json" in lines[0], err


def test_check_accepts_a_lens(sphere_10x24, tmp_path, capsys):
    root = tmp_path / "ds"
    shutil.copytree(sphere_10x24, root)
    tf = root / "transforms_train.json"
    d = json.loads(tf.read_text())
    d.update(camera_model="OPENCV", k1=-0.05, p1=1e-3)
    tf.write_text(json.dumps(d))
    assert main(["dataset", "check", str(root)]) == 0, capsys.readouterr().err


def test_check_refuses_an_unknown_model(sphere_10x24, tmp_path, capsys):
    _check_refuses(
        sphere_10x24,
        tmp_path,
        capsys,
        lambda d: d.update(camera_model="KANNALA"),
        "unknown camera_model",
    )


@pytest.mark.parametrize(
    "lens",
    [
        dict(camera_model="OPENCV", k1=-5.0),  # the radius turns back inside the image
        dict(camera_model="FULL_OPENCV", k1=0.0, k4=-12.0),  # the denominator crosses zero
        dict(camera_model="OPENCV_FISHEYE", k1=-3.0),
    ],
)
def test_check_refuses_a_folding_lens(sphere_10x24, tmp_path, capsys, lens):
    _check_refuses(sphere_10x24, tmp_path, capsys, lambda d: d.update(**lens), "folds the image")


def test_check_refuses_a_coefficient_the_model_lacks(sphere_10x24, tmp_path, capsys):
    _check_refuses(
        sphere_10x24,
        tmp_path,
        capsys,
        lambda d: d.update(camera_model="OPENCV_FISHEYE", p1=0.01),
        "'p1'",
    )
