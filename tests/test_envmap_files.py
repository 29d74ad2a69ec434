"""Environment maps in Radiance .hdr (checked against OpenCV's reader) and the panorama's
orientation in the world (scene.json's envmap_rotation, `dataset import --env-rotation`)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from clrefract.cli import main
from clrefract.dataset import Dataset
from clrefract.envmap import EnvMap, pixel_directions, rotation_matrix
from clrefract.errors import ClrefractError
from clrefract.imageio import read_hdr_rgb
from clrefract.loss import envmap_lookup_jacobian

cv2 = pytest.importorskip("cv2", reason="OpenCV, the oracle, is the test extra's")


def _write_hdr(path, rgb, rle=True):
    flag = cv2.IMWRITE_HDR_COMPRESSION_RLE if rle else cv2.IMWRITE_HDR_COMPRESSION_NONE
    assert cv2.imwrite(
        str(path),
        np.ascontiguousarray(rgb[..., ::-1], np.float32),
        [cv2.IMWRITE_HDR_COMPRESSION, flag],
    )


@pytest.mark.parametrize("rle", [True, False])
def test_hdr_reads_as_opencv_does(tmp_path, rle):
    rng = np.random.default_rng(3)
    img = np.exp(rng.uniform(-7, 7, (37, 64, 3))).astype(np.float32)  # 1e-3 .. 1e3
    img[5:9, 10:50] = [2.0, 0.5, 0.25]  # long runs, which RLE packs
    img[20, :] = 0.0
    path = tmp_path / "pano.hdr"
    _write_hdr(path, img, rle)
    ours = read_hdr_rgb(path)
    ref = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)[..., ::-1]
    np.testing.assert_array_equal(ours, ref)
    assert np.all(np.abs(ours - img) <= 0.01 * img.max(axis=-1, keepdims=True))
    env = EnvMap.from_file(path)
    np.testing.assert_array_equal(env.image, ref)


def test_bad_hdr_names_the_file(tmp_path):
    path = tmp_path / "pano.hdr"
    path.write_bytes(b"this is no panorama")
    with pytest.raises(ClrefractError, match="pano.hdr.*not a valid Radiance"):
        EnvMap.from_file(path)
    _write_hdr(path, np.ones((16, 32, 3), np.float32))
    path.write_bytes(path.read_bytes()[:-40])
    with pytest.raises(ClrefractError, match="pano.hdr.*truncated"):
        EnvMap.from_file(path)


def _rotated(env: EnvMap, rot: np.ndarray) -> np.ndarray:
    """The panorama that, turned by `rot` into the world, shows what `env` shows."""
    dirs = pixel_directions(env.width, env.height).reshape(-1, 3)
    return env.lookup(dirs @ rot.T).reshape(env.image.shape)


def _directions(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_rotation_keys():
    np.testing.assert_allclose(rotation_matrix([0, 0, 90]) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(rotation_matrix([90, 0, 0]) @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    r = rotation_matrix([10, -20, 30])
    np.testing.assert_allclose(rotation_matrix(r.tolist()), r)
    for bad in ([1, 2], [[2, 0, 0], [0, 1, 0], [0, 0, 1]], ["a", 0, 0], [np.nan, 0, 0]):
        with pytest.raises(ValueError):
            rotation_matrix(bad)


def test_a_turn_of_whole_pixels_looks_up_the_same():
    env = EnvMap.procedural(64, 32, seed=1)
    d = _directions(2000)
    for angles in ([0, 0, 90], [180, 0, -90], [180, 0, 45]):
        rot = rotation_matrix(angles)
        turned = EnvMap(_rotated(env, rot), rot)
        np.testing.assert_allclose(turned.lookup(d), env.lookup(d), rtol=1e-5, atol=1e-6)


def test_any_turn_looks_up_the_same_smooth_map():
    def f(d):  # smooth radiance over the sphere
        return np.stack([1.5 + d[:, 0], 1.5 + d[:, 1] * d[:, 2], 1.2 + 0.5 * d[:, 2]], -1)

    w, h = 1024, 512
    rot = rotation_matrix([25.0, -40.0, 70.0])
    env = EnvMap(f(pixel_directions(w, h).reshape(-1, 3) @ rot.T).reshape(h, w, 3), rot)
    d = _directions(5000, seed=2)
    np.testing.assert_allclose(env.lookup(d), f(d), atol=2e-3)
    # the blurred copies the fit uses keep the turn
    np.testing.assert_allclose(env.blurred(1.0).lookup(d), f(d), atol=5e-3)


def test_jacobian_of_a_turned_map():
    rot = rotation_matrix([25.0, -40.0, 70.0])
    env = EnvMap(EnvMap.procedural(256, 128, seed=4).blurred(3.0).image, rot)
    d = _directions(50, seed=5)
    rad, jac = envmap_lookup_jacobian(env, d)
    np.testing.assert_allclose(rad, env.lookup(d), rtol=1e-5)
    h = 1e-6
    # the lookup normalises its input: its derivative is the Jacobian on the tangent plane
    tangent = jac - np.einsum("ncj,nj,nk->nck", jac, d, d)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        num = (env.lookup(d + e).astype(np.float64) - env.lookup(d - e)) / (2 * h)
        err = np.abs(num - tangent[:, :, k])
        assert np.median(err) < 0.02 * np.median(np.abs(tangent[:, :, k])) + 1e-3, k


def test_import_a_turned_hdr_panorama(sphere_10x24, tmp_path, capsys):
    cap = tmp_path / "capture"
    shutil.copytree(sphere_10x24, cap)
    (cap / "scene.json").unlink()
    env = Dataset(sphere_10x24).envmap()
    rot = rotation_matrix([180.0, 0.0, 90.0])
    (cap / "envmap.exr").unlink()
    _write_hdr(cap / "envmap.hdr", _rotated(env, rot))
    out = tmp_path / "data"
    args = ["dataset", "import", cap, "--out", out, "--env-rotation", "180", "0", "90"]
    assert main([str(a) for a in args]) == 0, capsys.readouterr().err
    scene = json.loads((out / "scene.json").read_text())
    assert scene["envmap"] == "envmap.hdr" and scene["envmap_rotation"] == [180.0, 0.0, 90.0]
    assert main(["dataset", "check", str(out)]) == 0, capsys.readouterr()
    turned = Dataset(out)
    d = np.concatenate([c.rays()[1] for c in turned.train])
    a, b = turned.envmap().lookup(d), env.lookup(d)
    assert np.all(np.abs(a - b) <= 0.01 * b.max(axis=-1, keepdims=True) + 1e-6)


def _check_fails(capsys, root, *needles):
    code = main(["dataset", "check", str(root)])
    out, err = capsys.readouterr()
    lines = [ln for ln in out.splitlines() if all(n in ln for n in needles)]
    assert code == 2 and len(lines) == 1 and "Traceback" not in out + err, out + err


def test_check_refuses_a_bad_hdr_and_a_bad_rotation(sphere_10x24, tmp_path, capsys):
    root = tmp_path / "ds"
    shutil.copytree(sphere_10x24, root)
    scene = json.loads((root / "scene.json").read_text())
    (root / "scene.json").write_text(json.dumps({**scene, "envmap": "pano.hdr"}))
    (root / "pano.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X")
    _check_fails(capsys, root, "pano.hdr", "not a valid Radiance .hdr")
    (root / "scene.json").write_text(json.dumps({**scene, "envmap_rotation": [1, 2]}))
    _check_fails(capsys, root, "scene.json", "envmap_rotation")
