"""Equirectangular HDR environment map: lookup per SPEC section 6 and a procedural default."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from .errors import ClrefractError
from .imageio import HDR_SUFFIXES, PathLike, read_exr_rgb, read_hdr_rgb, write_exr_rgb


def pixel_directions(width: int, height: int) -> np.ndarray:
    """Unit direction (H, W, 3) float64 through each pixel centre (inverse of the lookup)."""
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = ((np.arange(width) + 0.5) / width - 0.5) * 2.0 * np.pi
    st = np.sin(theta)[:, None]
    return np.stack(
        np.broadcast_arrays(
            st * np.cos(phi)[None, :], st * np.sin(phi)[None, :], np.cos(theta)[:, None]
        ),
        axis=-1,
    )


MIN_WIDTH = 8  # pixels of the smallest environment map read from a file


def rotation_matrix(value) -> np.ndarray:
    """3x3 rotation from scene.json's `envmap_rotation`: [rx, ry, rz] degrees, turned about
    the world's x, then y, then z axis (R = Rz Ry Rx), or a 3x3 rotation matrix. ValueError
    for anything else."""
    try:
        m = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape == (3,) and np.isfinite(m).all():
        cx, cy, cz = np.cos(np.radians(m))
        sx, sy, sz = np.sin(np.radians(m))
        rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
        return rz @ ry @ rx
    if m.shape == (3, 3) and np.isfinite(m).all():
        if np.allclose(m.T @ m, np.eye(3), atol=1e-6) and np.linalg.det(m) > 0:
            return m
        raise ValueError("is a 3x3 matrix but not a rotation (scaled, sheared or mirrored)")
    raise ValueError(f"must be [rx, ry, rz] in degrees or a 3x3 rotation matrix, got {value!r}")


class EnvMap:
    """Linear radiance over the sphere, stored as an (H, W, 3) float32 lat-long image.

    `rotation` (3x3, or None for none) turns the panorama's own frame into the world's: the
    world direction d sees the panorama's pixel in direction rotation^T d."""

    def __init__(self, image: np.ndarray, rotation: np.ndarray | None = None):
        image = np.ascontiguousarray(image, dtype=np.float32)
        if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 1 or image.shape[1] < 1:
            raise ValueError(f"EnvMap: expected an (H, W, 3) image, got {image.shape}")
        self.image = image
        self.rotation = None if rotation is None else np.asarray(rotation, np.float64)
        if self.rotation is not None and np.array_equal(self.rotation, np.eye(3)):
            self.rotation = None

    def to_panorama(self, directions: np.ndarray) -> np.ndarray:
        """World directions (N, 3) float64 in the panorama's own frame."""
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        return d if self.rotation is None else d @ self.rotation

    @property
    def height(self) -> int:
        return self.image.shape[0]

    @property
    def width(self) -> int:
        return self.image.shape[1]

    @classmethod
    def from_file(cls, path: PathLike, rotation: np.ndarray | None = None) -> EnvMap:
        """The map of an EXR or a Radiance .hdr file (by its extension)."""
        is_hdr = str(path).lower().endswith(HDR_SUFFIXES)
        img = read_hdr_rgb(path) if is_hdr else read_exr_rgb(path)
        if not np.isfinite(img).all():
            raise ClrefractError(f"{path}: environment map has NaN or infinite pixels")
        h, w = img.shape[:2]
        if w < MIN_WIDTH or h < MIN_WIDTH // 2:
            # a lat-long map of a few pixels cannot show the object anything to refract
            raise ClrefractError(
                f"{path}: environment map is {w}x{h} pixels; a lat-long map needs at least "
                f"{MIN_WIDTH}x{MIN_WIDTH // 2}"
            )
        return cls(img, rotation)

    from_exr = from_file  # the name it had when only EXR was read

    def save(self, path: PathLike) -> None:
        write_exr_rgb(path, self.image)

    def lookup(self, directions: np.ndarray) -> np.ndarray:
        """Bilinear radiance (N, 3) float32 for directions (N, 3), which need not be unit.

        A zero vector looks at the horizon (u = 0.5, v = 0.5) rather than producing NaN.
        """
        d = self.to_panorama(directions)
        n = np.linalg.norm(d, axis=1)
        d = d / np.maximum(n, 1e-300)[:, None]
        h, w = self.height, self.width
        u = 0.5 + np.arctan2(d[:, 1], d[:, 0]) / (2.0 * np.pi)
        v = np.arccos(np.clip(d[:, 2], -1.0, 1.0)) / np.pi
        row = v * h - 0.5
        col = u * w - 0.5
        r0 = np.floor(row)
        c0 = np.floor(col)
        fr = (row - r0)[:, None]
        fc = (col - c0)[:, None]
        # Clamp in v (poles repeat the edge row), wrap in u (the seam at u = 0 / 1 is continuous).
        r0i = r0.astype(np.int64)
        r1 = np.clip(r0i + 1, 0, h - 1)
        r0i = np.clip(r0i, 0, h - 1)
        c0i = np.mod(c0.astype(np.int64), w)
        c1 = np.mod(c0i + 1, w)
        img = self.image
        top = img[r0i, c0i] * (1.0 - fc) + img[r0i, c1] * fc
        bot = img[r1, c0i] * (1.0 - fc) + img[r1, c1] * fc
        return (top * (1.0 - fr) + bot * fr).astype(np.float32)

    def blurred(self, sigma_px: float) -> EnvMap:
        """A copy blurred by a Gaussian of sigma_px pixels, wrapping in u, for coarse-to-fine."""
        if sigma_px <= 0:
            return EnvMap(self.image.copy(), self.rotation)
        out = gaussian_filter(
            self.image, sigma=(sigma_px, sigma_px, 0), mode=("nearest", "wrap", "nearest")
        )
        return EnvMap(out, self.rotation)

    @classmethod
    def procedural(cls, width: int = 1024, height: int = 512, seed: int = 0) -> EnvMap:
        return cls(procedural_image(width, height, seed))


# Plane-wave octaves: frequencies in cycles per radian-ish units of k . d, drawn up to a fixed
# maximum so that the same seed gives the same waves at every resolution; only those a map of
# the given size resolves (>= _MIN_WAVELENGTH_PX pixels per period) are summed.
_OCTAVES = 2.0 ** np.arange(1, 12)  # 2 .. 2048
_WAVES_PER_OCTAVE = 10
_MIN_WAVELENGTH_PX = 5.0
_N_LAMPS = 5
_MIN_LINE_SPACING_PX = 24.0


def procedural_image(width: int = 1024, height: int = 512, seed: int = 0) -> np.ndarray:
    """Seeded HDR lat-long image with structure at every scale and in every direction.

    Coloured sum of random plane waves on the sphere (smooth, no seam or pole artefacts),
    times a soft checker and a grid of thin dark lines, plus a few bright lamps (5 to 50).
    """
    if width < 4 or height < 2:
        raise ValueError(f"procedural envmap: size {width}x{height} too small")
    rng = np.random.default_rng(seed)
    n_waves = len(_OCTAVES) * _WAVES_PER_OCTAVE
    k = rng.normal(size=(n_waves, 3))
    k /= np.linalg.norm(k, axis=1, keepdims=True)
    freq = np.repeat(_OCTAVES, _WAVES_PER_OCTAVE) * 2.0 ** rng.uniform(0, 1, n_waves)
    phase = rng.uniform(0, 2 * np.pi, n_waves)
    # Flat-ish spectrum (amplitude ~ f^-0.3) keeps fine detail strong enough to see deflections.
    colour = rng.normal(size=(n_waves, 3)) * (freq**-0.3)[:, None]
    norm = np.sqrt(0.5 * (colour**2).sum(axis=0))  # std of the full sum, per channel
    lamp_dir = rng.normal(size=(_N_LAMPS, 3))
    lamp_dir /= np.linalg.norm(lamp_dir, axis=1, keepdims=True)
    lamp_radius = np.deg2rad(rng.uniform(1.5, 4.0, _N_LAMPS))
    lamp_value = rng.uniform(5.0, 50.0, _N_LAMPS)
    lamp_tint = rng.uniform(0.6, 1.0, (_N_LAMPS, 3))
    lamp_tint /= lamp_tint.max(axis=1, keepdims=True)

    keep = freq <= min(width, 2 * height) / _MIN_WAVELENGTH_PX
    kf = (k[keep] * freq[keep, None]).T.astype(np.float32)  # (3, n)
    ph = phase[keep].astype(np.float32)
    col = (colour[keep] / norm).astype(np.float32)

    dirs = pixel_directions(width, height).astype(np.float32)
    noise = np.empty((height, width, 3), np.float32)
    rows_per_chunk = max(1, (1 << 16) // width)  # bounds the (pixels, waves) temporary
    for r in range(0, height, rows_per_chunk):
        d = dirs[r : r + rows_per_chunk].reshape(-1, 3)
        noise[r : r + rows_per_chunk] = (np.sin(d @ kf + ph) @ col).reshape(-1, width, 3)
    img = 0.35 * np.exp(0.6 * noise)

    img *= checker_and_grid(width, height)[..., None]

    for ld, rad, val, tint in zip(lamp_dir, lamp_radius, lamp_value, lamp_tint, strict=True):
        ang = np.arccos(np.clip(dirs @ ld.astype(np.float32), -1.0, 1.0))
        edge = 2.0 * np.pi / width  # about a pixel of soft edge so bilinear lookup is smooth
        mask = 0.5 * (1.0 - np.tanh((ang - rad) / edge))
        img += (val * mask)[..., None] * tint.astype(np.float32)
    return img.astype(np.float32)


def checker_and_grid(width: int, height: int) -> np.ndarray:
    """(H, W) multiplier: soft 30-degree checker and dark lines every 10 degrees or more.

    Lines stay at least _MIN_LINE_SPACING_PX apart so small maps are not all grid.
    """
    x = np.arange(width) + 0.5  # pixel-centre coordinates in pixels
    y = np.arange(height) + 0.5
    phi = x / width * 2.0 * np.pi
    theta = y / height * np.pi
    # tanh of a sine: square wave whose edges are about two pixels wide.
    sharp_x, sharp_y = width / (2 * np.pi * 12), height / (np.pi * 6)
    cx = np.tanh(sharp_x * np.sin(12 * phi))
    cy = np.tanh(sharp_y * np.sin(6 * theta))
    checker = 1.0 + 0.15 * cy[:, None] * cx[None, :]

    def lines(coord: np.ndarray, spacing: float) -> np.ndarray:
        dist = np.abs(coord / spacing - np.round(coord / spacing)) * spacing
        return np.exp(-0.5 * (dist / 0.8) ** 2)

    px_per_deg = width / 360.0
    step_deg = next((d for d in (10, 15, 30, 45, 90) if d * px_per_deg >= _MIN_LINE_SPACING_PX), 90)
    sx, sy = width * step_deg / 360.0, height * step_deg / 180.0
    grid = np.maximum(lines(y, sy)[:, None], lines(x, sx)[None, :])
    return (checker * (1.0 - 0.5 * grid)).astype(np.float32)
