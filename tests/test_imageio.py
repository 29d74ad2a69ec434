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


def _fancy_upsample(c):
    """libjpeg's h2v2 'fancy' chroma upsampling written out: each output sample 3/4 of its
    nearest stored sample and 1/4 of the next one over, each way, edges replicated."""

    def one_axis(x, axis):
        x = np.moveaxis(x, axis, 0)
        prev = np.concatenate([x[:1], x[:-1]])
        nxt = np.concatenate([x[1:], x[-1:]])
        out = np.empty((2 * len(x), *x.shape[1:]))
        out[0::2], out[1::2] = (3 * x + prev) / 4, (3 * x + nxt) / 4
        return np.moveaxis(out, 0, axis)

    return one_axis(one_axis(c, 0), 1)


def test_stored_chroma_undoes_the_decoders_upsampling():
    """A 4:2:0 decode: luma per pixel, chroma samples per 2 x 2 block upsampled by libjpeg's
    triangle filter. stored_chroma gives back each block's sample (to float32 rounding) and
    keeps the luma; through Pillow's real encoder and decoder at quality 100 it comes nearer
    the encoder's samples (the 2 x 2 means of the original's chroma) than the decode does."""
    import io

    from PIL import Image

    from clrefract.imageio import YCC, stored_chroma

    rng = np.random.default_rng(3)
    h, w = 24, 32
    luma = 0.3 + 0.4 * rng.random((h, w))
    samples = 0.04 * rng.standard_normal((h // 2, w // 2, 2))
    ycc = np.concatenate([luma[..., None], _fancy_upsample(samples)], axis=2)
    decoded = ycc @ np.linalg.inv(YCC).T
    assert 0 < decoded.min() and decoded.max() < 1
    got = np.asarray(stored_chroma(decoded), np.float64) @ YCC.T
    assert np.abs(got[..., 0] - luma).max() < 1e-6
    want = samples.repeat(2, 0).repeat(2, 1)
    assert np.abs(got[..., 1:] - want).max() < 1e-6
    assert np.abs(ycc[..., 1:] - want).max() > 0.03  # what the decode alone is off by

    # Pillow's encoder and decoder (libjpeg-turbo), on colour that changes from block to
    # block, as refraction draws it: measured 0.023 off before, 0.002 after
    blocks = 0.05 * rng.standard_normal((16, 16, 2))
    flat = np.concatenate([np.full((32, 32, 1), 0.5), blocks.repeat(2, 0).repeat(2, 1)], 2)
    u8 = np.round(flat @ np.linalg.inv(YCC).T * 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(u8).save(buf, "JPEG", quality=100, subsampling=2)
    dec = np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"), np.float64) / 255

    def block_chroma(x):
        c = (np.asarray(x, np.float64) @ YCC.T)[..., 1:]
        return c.reshape(16, 2, 16, 2, 2).mean(axis=(1, 3))

    truth = block_chroma(u8 / 255.0)
    before = np.sqrt(((block_chroma(dec) - truth) ** 2).mean())
    after = np.sqrt(((block_chroma(stored_chroma(dec)) - truth) ** 2).mean())
    assert after < 0.2 * before, (after, before)
