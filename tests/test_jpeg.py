"""jpeg.py: a 4:2:0 JPEG file's quantisation bins, read back from its decoded pixels, against
the coefficients an encoder computes from the original image (an explicit cosine basis,
not the module's FFT); the image nearest a render that the file allows; and the jpeg loss
on the true sphere."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from clrefract.imageio import YCC, stored_chroma
from clrefract.jpeg import MB, columns, consistent, read_bins


def cosine_basis() -> np.ndarray:
    """JPEG's 8-point DCT-II as a matrix: C[u, x] = a(u) cos((2x + 1) u pi / 16)."""
    u, x = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
    c = np.cos((2 * x + 1) * u * np.pi / 16) / 2
    c[0] /= np.sqrt(2)
    return c


@pytest.fixture(scope="module")
def photo(tmp_path_factory):
    """A smooth colour image of 40 x 56 (partial macroblocks at two edges) with some edges,
    stored as a quality-90 4:2:0 JPEG: (original in [0, 1], decoded, path)."""
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:40, 0:56] / 8.0
    img = np.stack(
        [0.5 + 0.3 * np.sin(x * (1 + k) + y * (2 - k) + rng.uniform(0, 6)) for k in range(3)], -1
    )
    img[12:30, 20:44] = (0.9, 0.2, 0.3)  # a colour edge, as refraction draws them
    u8 = np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
    path = tmp_path_factory.mktemp("jpeg") / "frame.jpg"
    Image.fromarray(u8).save(path, quality=90, subsampling=2)
    decoded = np.asarray(Image.open(path), np.float64) / 255
    return u8.astype(np.float64) / 255, decoded, path


def test_the_bins_reproduce_what_the_decoder_drew(photo):
    """A decoder draws each 8 x 8 block as the inverse DCT of its stored coefficients (bin
    index times step), rounded to 8 bits. The bins read back reproduce the decoded luma so,
    per pixel within that rounding and per block on average within 0.2 of a level (measured
    0.10; one bin off in the mean coefficient alone moves it 3 / 8 of a level), and so do
    the chroma samples the file stored (0.09)."""
    _, decoded, path = photo
    bins = read_bins(path)
    assert bins.k_luma.shape == (6, 8, 8, 8) and bins.k_chroma.shape == (2, 3, 4, 8, 8)
    c = cosine_basis()
    drawn = np.einsum("ux,abuv,vy->abxy", c, bins.k_luma * bins.q_luma, c) + 128
    ycc = stored_chroma(decoded).astype(np.float64) @ YCC.T * 255
    seen = ycc[:, :, 0].reshape(5, 8, 7, 8).transpose(0, 2, 1, 3)  # the whole blocks
    diff = drawn[:5, :7] - seen
    assert np.abs(diff).max() < 1.0, np.abs(diff).max()
    assert np.abs(diff.mean(axis=(2, 3))).max() < 0.2, np.abs(diff.mean(axis=(2, 3))).max()
    samples = np.moveaxis(ycc[::2, ::2, 1:], -1, 0)  # (2, 20, 28): whole chroma blocks 2 x 3
    drawn_c = np.einsum("ux,kabuv,vy->kabxy", c, bins.k_chroma * bins.q_chroma, c)
    seen_c = samples[:, :16, :24].reshape(2, 2, 8, 3, 8).transpose(0, 1, 3, 2, 4)
    diff_c = drawn_c[:, :2, :3] - seen_c
    assert np.abs(diff_c).max() < 2.0 and np.abs(diff_c.mean(axis=(3, 4))).max() < 0.2


def macroblock_rays(h: int, w: int):
    """Every macroblock of an h x w frame as jpeg.columns lays their rays out: (top-left
    rows, columns, pixel index of each ray)."""
    ys, xs = np.meshgrid(np.arange(0, h, MB), np.arange(0, w, MB), indexing="ij")
    y0, x0 = ys.ravel(), xs.ravel()
    dy, dx = np.divmod(np.arange(MB * MB), MB)
    rows = np.minimum(y0[:, None] + dy, h - 1)
    cols = np.minimum(x0[:, None] + dx, w - 1)
    return y0, x0, (rows * w + cols).ravel()


def test_the_decoded_file_stays_and_a_render_moves_to_the_nearest_image_it_allows(photo):
    """The decoded photograph is an image its file allows: `consistent` leaves it. The
    original (what a perfect render would show) moves to an image nearer it than the decoded
    one, with its luma coefficients inside their bins."""
    original, decoded, path = photo
    bins = read_bins(path)
    y0, x0, pix = macroblock_rays(40, 56)
    cols = columns([bins], np.zeros(len(y0), int), y0, x0)
    ycc_dec = stored_chroma(decoded).reshape(-1, 3)[pix] @ YCC.T * 255
    np.testing.assert_allclose(consistent(ycc_dec, cols), ycc_dec, atol=1e-9)
    ycc = original.reshape(-1, 3)[pix] @ YCC.T * 255
    near = consistent(ycc, cols)
    inner = (y0 + MB <= 40) & (x0 + MB <= 56)  # whole macroblocks: no repeated edge rays
    rays = np.repeat(inner, MB * MB)
    luma = lambda v: np.sum((v[rays, 0] - ycc[rays, 0]) ** 2)  # noqa: E731
    assert luma(near) < 0.8 * luma(ycc_dec), (luma(near), luma(ycc_dec))
    blocks = near[rays, 0].reshape(-1, 2, 8, 2, 8).transpose(0, 1, 3, 2, 4) - 128
    c = cosine_basis()
    coef = np.einsum("ux,mabxy,vy->mabuv", c, blocks, c)
    centre = cols[rays, 0].reshape(-1, 2, 8, 2, 8).transpose(0, 1, 3, 2, 4)
    step = cols[rays, 1].reshape(-1, 2, 8, 2, 8).transpose(0, 1, 3, 2, 4)
    assert np.all(np.abs(coef - centre) <= step / 2 + 1e-9)


def test_the_jpeg_loss_leaves_little_at_the_truth_where_srgb420_leaves_the_files_error(
    tmp_path,
):
    """The true sphere against its noisy 4:2:0 JPEG views (quality 90, 12 of 48 x 48): the
    srgb420 residual at the truth is the file's quantisation and the sensor's noise, nearly
    all of its loss an index 0.003 off (measured 0.98); the jpeg loss keeps only what no bin
    explains (0.72), so a wrong index adds 24 times as much over its floor."""
    from clrefract.dataset import Dataset, frame_gain
    from clrefract.fields.interface import SphereInterface
    from clrefract.interface import InterfaceTracer
    from clrefract.loss import photometric_loss
    from clrefract.realistic import parse_flaws
    from clrefract.synth import MakeOptions, make_dataset
    from clrefract.tracer import renders_black

    opt = MakeOptions(views=12, res=48, env_width=512, volume_res=16)
    opt.realistic = parse_flaws("full_well=4000,read_noise=0.001,jpeg=90")
    make_dataset("sphere", tmp_path / "d", opt)
    ds = Dataset(tmp_path / "d")
    ds.train_chroma = "stored"
    env = ds.envmap()
    y0, x0, pix = macroblock_rays(48, 48)
    losses = {}
    for eta in (1.5, 1.503):
        tracer = InterfaceTracer(SphereInterface((0.0, 0.0, 0.0), 20.0, eta, ds.box), ds.box)
        for cam in ds.train:
            img, weight = ds.frame(cam)
            o, d = cam.rays()
            res = tracer.trace(o[pix], d[pix])
            target = img.reshape(-1, 3)[pix].astype(np.float64)
            cols = columns([read_bins(ds.frame_path(cam))], np.zeros(len(y0), int), y0, x0)
            gain = np.broadcast_to(frame_gain(cam), target.shape)
            for space, t in (("srgb420", target), ("jpeg", np.hstack([target, gain, cols]))):
                loss = photometric_loss(
                    env, res.direction, t, weight.ravel()[pix], space, renders_black(res.status)
                )[0]
                losses[space, eta] = losses.get((space, eta), 0.0) + loss
    ratio = {s: losses[s, 1.5] / losses[s, 1.503] for s in ("srgb420", "jpeg")}
    rise = {s: 1 / r - 1 for s, r in ratio.items()}  # what the wrong index adds, over the floor
    assert ratio["jpeg"] < 0.85 and rise["jpeg"] > 8 * rise["srgb420"], ratio
