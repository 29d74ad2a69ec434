"""Cameras: ray conventions (SPEC section 6), generators, transforms JSON round trip and errors."""

import json
import math

import numpy as np
import OpenEXR
import pytest

from clrefract.cameras import (
    Camera,
    fibonacci_sphere_cameras,
    load_transforms,
    look_at,
    orbit_cameras,
    save_transforms,
)
from clrefract.errors import ClrefractError


def _angle_deg(a, b):
    c = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(np.clip(c, -1, 1)))


def test_look_at_axes():
    c2w = look_at([200.0, 0, 0])
    r = c2w[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(-r[:, 2], [-1, 0, 0], atol=1e-12)  # looks at the origin
    np.testing.assert_allclose(r[:, 1], [0, 0, 1], atol=1e-12)  # image up is world up
    np.testing.assert_allclose(c2w[:3, 3], [200, 0, 0])
    # Looking straight down the up axis still gives a proper rotation.
    top = look_at([0, 0, 50.0])
    np.testing.assert_allclose(top[:3, :3].T @ top[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(-top[:3, 2], [0, 0, -1], atol=1e-12)


def test_centre_and_corner_rays():
    cam = fibonacci_sphere_cameras(10, radius=200.0, width=64, height=64, fov_y_deg=30.0)[3]
    o, d = cam.rays()
    assert o.shape == d.shape == (64 * 64, 3) and d.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(o, axis=1), 200.0)
    look = -cam.c2w[:3, 2]
    np.testing.assert_allclose(look, -o[0] / 200.0, atol=1e-12)  # looks at the origin
    # Even size: the four pixels around the centre are half a pixel off the axis, symmetrically.
    d = d.reshape(64, 64, 3)
    half_px = math.degrees(math.atan(math.hypot(0.5, 0.5) / cam.fl_x))
    for i, j in [(31, 31), (31, 32), (32, 31), (32, 32)]:
        assert _angle_deg(d[i, j], look) == pytest.approx(half_px, rel=1e-9)
    np.testing.assert_allclose(
        (d[31, 31] + d[32, 32]) / 2 / np.linalg.norm((d[31, 31] + d[32, 32]) / 2), look, atol=1e-12
    )
    # Top-left pixel centre: half a pixel inside the corner of a 30-degree vertical fov.
    t = math.tan(math.radians(15)) * (31.5 / 32)
    assert _angle_deg(d[0, 0], look) == pytest.approx(math.degrees(math.atan(t * math.sqrt(2))))
    # Row 0 is the top of the image: it points more along the camera's +y than the last row.
    up = cam.c2w[:3, 1]
    assert d[0, 32] @ up > 0 > d[63, 32] @ up
    right = cam.c2w[:3, 0]
    assert d[32, 63] @ right > 0 > d[32, 0] @ right


def test_rays_match_spec_formula_non_square():
    c2w = look_at([10.0, -20, 5], target=[1, 2, 3])
    cam = Camera(6, 4, fl_x=5.0, fl_y=7.0, cx=2.5, cy=1.75, c2w=c2w)
    _, d = cam.rays()
    i, j = 2, 5
    want = c2w[:3, :3] @ np.array([(j + 0.5 - 2.5) / 5.0, -(i + 0.5 - 1.75) / 7.0, -1.0])
    np.testing.assert_allclose(d[i * 6 + j], want / np.linalg.norm(want), atol=1e-12)


def test_fibonacci_cameras_spread_and_fov():
    cams = fibonacci_sphere_cameras(100)
    assert len(cams) == 100
    pos = np.array([c.position for c in cams])
    np.testing.assert_allclose(np.linalg.norm(pos, axis=1), 200.0)
    assert abs(pos.mean(axis=0)).max() < 5.0  # evenly spread
    c = cams[0]
    assert (c.width, c.height) == (128, 128) and c.fl_x == c.fl_y
    assert c.cx == 64 and c.cy == 64
    assert math.degrees(2 * math.atan(c.height / 2 / c.fl_y)) == pytest.approx(30.0)
    assert len({c.name for c in cams}) == 100


def test_orbit_cameras():
    cams = orbit_cameras(8, radius=150.0, elevation_deg=30.0, width=32, height=24, fov_y_deg=40)
    pos = np.array([c.position for c in cams])
    np.testing.assert_allclose(pos[:, 2], 150 * math.sin(math.radians(30)))
    np.testing.assert_allclose(np.linalg.norm(pos, axis=1), 150.0)
    assert cams[0].width == 32 and cams[0].height == 24 and cams[0].fl_x == cams[0].fl_y


def test_transforms_round_trip(tmp_path):
    cams = fibonacci_sphere_cameras(5, width=40, height=30)
    cams[2] = Camera(20, 10, 17.0, 18.0, 9.5, 5.25, cams[2].c2w, file_path="./odd/img_2")
    p = tmp_path / "transforms_train.json"
    save_transforms(p, cams, extra={"scene": "sphere"})
    raw = json.loads(p.read_text())
    assert raw["scene"] == "sphere" and raw["w"] == 40 and raw["h"] == 30
    assert "camera_angle_x" in raw and "fl_x" not in raw["frames"][0]
    assert raw["frames"][2]["fl_x"] == 17.0  # differing intrinsics go per frame
    back = load_transforms(p)
    assert len(back) == 5
    for a, b in zip(cams, back, strict=True):
        assert (a.width, a.height) == (b.width, b.height)
        for k in ("fl_x", "fl_y", "cx", "cy"):
            assert getattr(a, k) == pytest.approx(getattr(b, k), rel=1e-12)
        np.testing.assert_array_equal(a.c2w, b.c2w)
    assert back[0].file_path == "view_000" and back[2].file_path == "./odd/img_2"
    assert back[2].name == "img_2"


def _write(tmp_path, obj, name="t.json"):
    p = tmp_path / name
    p.write_text(obj if isinstance(obj, str) else json.dumps(obj))
    return p


EYE = look_at([0, -200.0, 0]).tolist()


def test_camera_angle_x_only_with_w_h(tmp_path):
    p = _write(
        tmp_path,
        {
            "camera_angle_x": 0.6,
            "w": 80,
            "h": 60,
            "frames": [{"file_path": "a", "transform_matrix": EYE}],
        },
    )
    (c,) = load_transforms(p)
    assert c.fl_x == pytest.approx(80 / (2 * math.tan(0.3)))
    assert c.fl_y == c.fl_x and c.cx == 40 and c.cy == 30


def test_size_from_image_header(tmp_path):
    (tmp_path / "train").mkdir()
    OpenEXR.File({}, {"RGB": np.zeros((12, 20, 3), np.float32)}).write(
        str(tmp_path / "train" / "r_0.exr")
    )
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "train" / "r_1.png", np.zeros((9, 14, 3), np.uint8))
    p = _write(
        tmp_path,
        {
            "camera_angle_x": 0.5,
            "frames": [
                {"file_path": "./train/r_0", "transform_matrix": EYE},
                {"file_path": "./train/r_1.png", "transform_matrix": EYE},
            ],
        },
    )
    a, b = load_transforms(p)
    assert (a.width, a.height) == (20, 12) and (b.width, b.height) == (14, 9)


def test_per_frame_intrinsics_override(tmp_path):
    p = _write(
        tmp_path,
        {
            "fl_x": 50.0,
            "w": 64,
            "h": 48,
            "frames": [
                {"file_path": "a", "transform_matrix": EYE},
                {"file_path": "b", "transform_matrix": EYE, "fl_x": 70.0, "fl_y": 71.0, "cx": 30.0},
            ],
        },
    )
    a, b = load_transforms(p)
    assert (a.fl_x, a.fl_y, a.cx, a.cy) == (50.0, 50.0, 32.0, 24.0)
    assert (b.fl_x, b.fl_y, b.cx, b.cy) == (70.0, 71.0, 30.0, 24.0)


BAD = {
    "not json": ("{frames: nope", "not valid JSON"),
    "list top": ([1, 2], "JSON object"),
    "no frames": ({"camera_angle_x": 0.5, "w": 8, "h": 8}, "'frames'"),
    "empty frames": ({"camera_angle_x": 0.5, "w": 8, "h": 8, "frames": []}, "empty"),
    "frame not obj": ({"camera_angle_x": 0.5, "w": 8, "h": 8, "frames": [3]}, r"frames\[0\]"),
    "no matrix": (
        {"camera_angle_x": 0.5, "w": 8, "h": 8, "frames": [{"file_path": "a"}]},
        "transform_matrix",
    ),
    "3x4": (
        {
            "camera_angle_x": 0.5,
            "w": 8,
            "h": 8,
            "frames": [{"file_path": "a", "transform_matrix": EYE[:3]}],
        },
        "4x4",
    ),
    "ragged": (
        {
            "camera_angle_x": 0.5,
            "w": 8,
            "h": 8,
            "frames": [{"file_path": "a", "transform_matrix": [[1, 0], [0, 1, 0, 0]]}],
        },
        "4x4",
    ),
    "strings": (
        {
            "camera_angle_x": 0.5,
            "w": 8,
            "h": 8,
            "frames": [{"file_path": "a", "transform_matrix": "eye"}],
        },
        "4x4",
    ),
    "nan": (
        {
            "camera_angle_x": 0.5,
            "w": 8,
            "h": 8,
            "frames": [{"file_path": "a", "transform_matrix": [[float("nan")] * 4] * 4}],
        },
        "non-finite",
    ),
    "scaled": (
        {
            "camera_angle_x": 0.5,
            "w": 8,
            "h": 8,
            "frames": [{"file_path": "a", "transform_matrix": (np.diag([2.0, 2, 2, 1])).tolist()}],
        },
        "not a rotation",
    ),
    "no intrinsics": (
        {"w": 8, "h": 8, "frames": [{"file_path": "a", "transform_matrix": EYE}]},
        "missing intrinsics",
    ),
    "no size": (
        {"camera_angle_x": 0.5, "frames": [{"file_path": "a", "transform_matrix": EYE}]},
        "image size unknown",
    ),
    "bad w": (
        {
            "camera_angle_x": 0.5,
            "w": -3,
            "h": 8,
            "frames": [{"file_path": "a", "transform_matrix": EYE}],
        },
        "'w' must be positive",
    ),
    "text fl": (
        {"fl_x": "big", "w": 8, "h": 8, "frames": [{"file_path": "a", "transform_matrix": EYE}]},
        "'fl_x'",
    ),
    "distortion": (
        {
            "fl_x": 5.0,
            "w": 8,
            "h": 8,
            "k1": -5.0,
            "frames": [{"file_path": "a", "transform_matrix": EYE}],
        },
        "distortion.*folds",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_transforms_name_the_file(tmp_path, case):
    obj, msg = BAD[case]
    p = _write(tmp_path, obj, name="broken_transforms.json")
    with pytest.raises(ClrefractError, match=msg) as e:
        load_transforms(p)
    assert "broken_transforms.json" in str(e.value)


def test_missing_transforms_file(tmp_path):
    with pytest.raises(ClrefractError, match="gone.json.*not found"):
        load_transforms(tmp_path / "gone.json")


def test_garbage_image_for_size_is_user_error(tmp_path):
    (tmp_path / "a.png").write_bytes(b"junk")
    p = _write(
        tmp_path,
        {"camera_angle_x": 0.5, "frames": [{"file_path": "a.png", "transform_matrix": EYE}]},
    )
    with pytest.raises(ClrefractError, match="a.png"):
        load_transforms(p)
