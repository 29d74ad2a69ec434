"""EXR / PNG I/O: round trips and user-facing errors."""

import numpy as np
import OpenEXR
import pytest

from clrefract.errors import ClrefractError
from clrefract.imageio import linear_to_srgb, read_exr_rgb, write_exr_rgb, write_png_srgb


def test_exr_float32_round_trip_is_exact(tmp_path):
    img = np.random.default_rng(1).uniform(0, 40, (7, 11, 3)).astype(np.float32)
    p = tmp_path / "a.exr"
    write_exr_rgb(p, img)
    back = read_exr_rgb(p)
    assert back.dtype == np.float32 and back.shape == (7, 11, 3)
    np.testing.assert_array_equal(back, img)
    assert [f.name for f in tmp_path.iterdir()] == ["a.exr"]  # no temp file left behind


def test_exr_half_round_trip_within_tolerance(tmp_path):
    img = np.random.default_rng(2).uniform(0, 40, (5, 6, 3)).astype(np.float32)
    p = tmp_path / "h.exr"
    write_exr_rgb(p, img, half=True)
    back = read_exr_rgb(p)
    assert back.dtype == np.float32
    np.testing.assert_allclose(back, img, rtol=1e-3, atol=1e-3)


def test_exr_layer_prefixed_channels(tmp_path):
    img = np.random.default_rng(3).uniform(0, 1, (4, 5, 3)).astype(np.float32)
    p = tmp_path / "l.exr"
    chans = {f"rgba.{c}": img[..., k].copy() for k, c in enumerate("RGB")}
    OpenEXR.File({}, chans).write(str(p))
    np.testing.assert_array_equal(read_exr_rgb(p), img)


def test_missing_exr_names_file(tmp_path):
    p = tmp_path / "nothere.exr"
    with pytest.raises(ClrefractError, match="nothere.exr.*not found"):
        read_exr_rgb(p)


def test_garbage_exr_names_file(tmp_path):
    p = tmp_path / "garbage.exr"
    p.write_bytes(b"this is not an exr file" * 10)
    with pytest.raises(ClrefractError, match="garbage.exr.*not a readable EXR"):
        read_exr_rgb(p)


def test_exr_without_rgb_names_file_and_channels(tmp_path):
    p = tmp_path / "lum.exr"
    OpenEXR.File({}, {"Y": np.ones((3, 4), np.float32)}).write(str(p))
    with pytest.raises(ClrefractError, match=r"lum.exr.*no R, G, B.*Y"):
        read_exr_rgb(p)


def test_write_into_missing_dir_is_user_error(tmp_path):
    with pytest.raises(ClrefractError, match="nodir"):
        write_exr_rgb(tmp_path / "nodir" / "x.exr", np.zeros((2, 2, 3), np.float32))


def test_linear_to_srgb_known_values():
    x = np.array([-1.0, 0.0, 0.002, 0.0031308, 0.18, 0.5, 1.0, 7.0, np.nan], np.float32)
    y = linear_to_srgb(x)
    assert y[0] == 0 and y[1] == 0 and y[-1] == 0
    assert y[2] == pytest.approx(12.92 * 0.002, rel=1e-6)
    assert y[3] == pytest.approx(0.04045, abs=1e-5)  # the two branches meet here
    assert y[4] == pytest.approx(0.46135, abs=1e-4)
    assert y[5] == pytest.approx(0.73536, abs=1e-4)
    assert y[6] == pytest.approx(1.0, abs=1e-6) and y[7] == pytest.approx(1.0, abs=1e-6)


def test_png_srgb_written(tmp_path):
    import imageio.v3 as iio

    img = np.zeros((3, 4, 3), np.float32)
    img[0, 0] = 1.0
    img[1, 1] = 0.18
    p = tmp_path / "p.png"
    write_png_srgb(p, img)
    back = iio.imread(p)
    assert back.dtype == np.uint8 and back.shape == (3, 4, 3)
    assert tuple(back[0, 0]) == (255, 255, 255)
    assert back[1, 1, 0] == round(0.46135 * 255)
    assert back[2, 2, 0] == 0
