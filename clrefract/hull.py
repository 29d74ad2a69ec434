"""Where the object can be: refraction masks and their visual hull, to start a fit.

A pixel whose ray passes only through air sees the environment straight along the ray.
Where the photograph differs from that straight lookup, the ray crossed the object (the
environment has detail everywhere). Carving the box with these masks from every view gives
the visual hull: no refraction happens outside it. A fit that starts from the hull filled
with one index, chosen by a line search on the loss, and updates only the hull, avoids the
local minima of an empty start (a solid must reach a large index before it beats empty
space) and the streaks a fit otherwise leaves in empty space.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .cameras import Camera
from .envmap import EnvMap
from .fields.base import Box
from .loss import srgb

SOLIDITY = 0.5  # below this fraction of its convex hull, a mask is edge arcs
TOLERANCE = 0.03  # fraction of the views a hull point may lie outside (masks' small holes)
CARVE_MAX = 0.02  # share of the others' core a view may carve before its mask is left out
CORE_TOLERANCE = 0.2  # the core the views agree on: inside all of them but a fifth
# A real capture's background differs a little from the panorama everywhere (sensor noise,
# JPEG, a pose off by a tenth of a degree): where NOISE_K times the lower quartile of the
# pixels' differences passes the threshold, the two are compared blurred by NOISE_BLUR_PX,
# against that raised threshold (at most NOISE_CAP: refraction differs by more, and an object
# that fills the frame sets the quartile itself), and the thin lines that misregistration
# leaves are opened away. On the realistic sphere (`dataset make --realistic`) this took the
# masks from 95-99% of each view to an IoU of 0.94 with the clean dataset's; clean datasets
# (a quartile of 0) are untouched.
NOISE_K = 6.0
NOISE_QUANTILE = 25
NOISE_CAP = 0.15
NOISE_BLUR_PX = 0.7


@dataclass
class Hull:
    distance: np.ndarray  # (n, n, n) signed distance (mm) to the hull on the nodes, + inside
    width: float  # mm over which the occupancy goes from 0 to 1
    mask_fraction: float  # mean fraction of training pixels marked as refracting
    rejected: tuple = ()  # views whose masks carved the others' core, left out

    def shell(self, offset: float = 0.0) -> np.ndarray:
        """Occupancy in [0, 1] of the hull grown by `offset` mm (shrunk when negative)."""
        t = np.clip((self.distance + offset) / self.width + 0.5, 0.0, 1.0)
        return t * t * t * (t * (t * 6 - 15) + 10)

    def smoothed(self, sigma: float) -> Hull:
        """The hull with its signed distance blurred by a Gaussian of sigma mm: rounds the
        facets a finite set of views leaves between their silhouette cones."""
        if sigma <= 0:
            return self
        far = 8 * self.width + 3 * sigma
        d = ndimage.gaussian_filter(np.clip(self.distance, -far, far), sigma / self.width)
        return Hull(d, self.width, self.mask_fraction)

    def hollowed(self, depth: float) -> Hull:
        """The shell of the hull `depth` mm deep under its surface."""
        d = np.minimum(self.distance, depth - self.distance)
        return Hull(d, self.width, self.mask_fraction, self.rejected)

    def graded(self, power: float) -> GradedHull:
        """The hull filled by a profile that rises from its surface to its deepest point."""
        return GradedHull(self.distance, self.width, self.mask_fraction, self.rejected, power)

    @property
    def occupancy(self) -> np.ndarray:
        return self.shell(0.0)

    @property
    def found(self) -> bool:
        """At least a few nodes inside: faint media (gas) mark too few pixels to carve."""
        return int((self.occupancy > 0.5).sum()) >= 8

    def dilated(self, cells: int) -> np.ndarray:
        """Nodes within `cells` of the hull (where a fit may change eta)."""
        inside = self.occupancy > 0.5
        if cells <= 0 or not inside.any():
            return inside
        return ndimage.binary_dilation(inside, iterations=cells)


@dataclass
class GradedHull(Hull):
    """A graded medium's hull: `shell` is 1 - (1 - u)^power of the depth u (0 at the surface,
    1 at the deepest point; grown or shrunk by the offset), not an occupancy. At power 2 it
    is the parabolic profile of graded-index rods and lenses; as the power grows it tends to
    the solid hull."""

    power: float = 2.0

    @property
    def occupancy(self) -> np.ndarray:
        return super().shell(0.0)

    def shell(self, offset: float = 0.0) -> np.ndarray:
        d = self.distance + offset
        u = np.clip(d / max(float(d.max()), 1e-12), 0.0, 1.0)
        return 1.0 - (1.0 - u) ** self.power


def refraction_mask(
    cam: Camera, image: np.ndarray, env: EnvMap, threshold: float = 0.05
) -> np.ndarray:
    """(H, W) bool: pixels whose photograph differs from the environment seen straight, with
    the holes inside the silhouette filled."""
    _, d = cam.rays()
    straight = env.lookup(d).reshape(cam.height, cam.width, 3)
    diff = np.abs(srgb(image)[0] - srgb(straight)[0]).max(axis=-1)
    noisy = NOISE_K * float(np.percentile(diff, NOISE_QUANTILE)) > threshold
    if noisy:
        blur = (NOISE_BLUR_PX, NOISE_BLUR_PX, 0)
        smooth = [srgb(ndimage.gaussian_filter(x, blur))[0] for x in (image, straight)]
        diff = np.abs(smooth[0] - smooth[1]).max(axis=-1)
        noise = NOISE_K * float(np.percentile(diff, NOISE_QUANTILE))
        threshold = max(threshold, min(noise, NOISE_CAP))
    marked = ndimage.median_filter(diff, size=3) > threshold
    if noisy:
        marked = ndimage.binary_opening(marked)
    # closed with the frame's edge pixels carried on beyond it: closing erodes what touches
    # the border otherwise, and an object that runs off the frame would stop short of it
    pad = 2
    marked = np.pad(marked, pad, mode="edge")
    mask = ndimage.binary_closing(marked, iterations=pad)[pad:-pad, pad:-pad]
    mask = ndimage.binary_fill_holes(mask)
    # a ray through two parallel faces leaves parallel to how it came, shifted: with the
    # environment at infinity it looks like air, so a flat-faced object (a cube, a prism)
    # seen face-on leaves only arcs along its edges. A mask that fills less than half of its
    # convex hull is taken to be such arcs, and replaced by that hull: an over-estimate
    # (the fit's offset search and gradient shrink it), never a hole in the object.
    if mask.sum() >= 8:
        from skimage.morphology import convex_hull_image

        hull = convex_hull_image(mask)
        if mask.sum() < SOLIDITY * hull.sum():
            mask = hull
    return mask


def touches_frame(mask: np.ndarray) -> bool:
    """The mask reaches the picture's edge: the object may go on beyond the frame."""
    return bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def mask_distance(mask: np.ndarray) -> np.ndarray:
    """Signed distance to the mask's boundary in pixels, positive inside."""
    inside = ndimage.distance_transform_edt(mask)
    outside = ndimage.distance_transform_edt(~mask)
    return np.where(mask, inside - 0.5, 0.5 - outside)


def project(cam: Camera, pts: np.ndarray):
    """Pixel row, column (continuous, pixel centres at +0.5) and depth of world points (n, 3);
    depth <= 0 behind the camera."""
    w2c = np.linalg.inv(cam.c2w)
    p = pts @ w2c[:3, :3].T + w2c[:3, 3]
    depth = -p[:, 2]
    z = np.where(depth > 1e-9, depth, 1.0)
    if cam.distortion:  # through the lens (OpenCV's image coordinates: y down)
        x, y = cam.distort(p[:, 0] / z, -p[:, 1] / z)
        return cam.cy + cam.fl_y * y, cam.cx + cam.fl_x * x, depth
    col = cam.cx + cam.fl_x * p[:, 0] / z
    row = cam.cy - cam.fl_y * p[:, 1] / z
    return row, col, depth


def cone_distances(cameras: list[Camera], dists: list[np.ndarray], p: np.ndarray):
    """(views, n): signed distance (mm, + inside) of points to each view's silhouette cone,
    read bilinearly from the mask's distance transform at the point's depth; inf where a
    point is behind the view. Beyond the frame the mask's edge goes on: air where the edge is
    air (the object is in the frame), unknown (inside) where the mask runs off the frame."""
    sd = np.full((len(cameras), len(p)), np.inf)
    for v, (cam, dist) in enumerate(zip(cameras, dists)):
        row, col, depth = project(cam, p)
        ok = depth > 0
        if not ok.any():
            continue
        # pixel centres sit at +0.5; map_coordinates samples centres at integers
        r = np.clip(row[ok] - 0.5, 0.0, cam.height - 1.0)
        c = np.clip(col[ok] - 0.5, 0.0, cam.width - 1.0)
        px = ndimage.map_coordinates(dist, [r, c], order=1, mode="nearest")
        beyond = np.hypot(row[ok] - 0.5 - r, col[ok] - 0.5 - c)
        px = np.where(px < 0, px - beyond, px)
        sd[v, ok] = px * depth[ok] / cam.fl_x
    return sd


def _kth(sd: np.ndarray, tolerance: float, nearest: bool = False) -> np.ndarray:
    """Per point, the smallest cone distance but for a `tolerance` fraction of the views
    that see it, rounded down (or to the nearest count: one view of 17 to 50 instead of
    none, and still none of 4); -inf where no view sees it (all behind it)."""
    seen = np.isfinite(sd).sum(axis=0)
    k = (np.rint if nearest else np.floor)(tolerance * seen).astype(np.int64)
    k = np.minimum(k, np.maximum(seen - 1, 0))
    val = np.take_along_axis(np.sort(sd, axis=0), k[None], axis=0)[0]
    return np.where(seen > 0, val, -np.inf)


def hull_distance(
    box: Box,
    cameras: list[Camera],
    masks: list[np.ndarray],
    pts: np.ndarray,
    tolerance: float = TOLERANCE,
    chunk: int = 65536,
    dists: list[np.ndarray] | None = None,
):
    """Signed distance (mm, positive inside) of points to the visual hull: the distance to
    each view's silhouette cone, then the smallest over the views but for a `tolerance`
    fraction of them (to the nearest count), whose masks may have small holes. Points
    behind every view get -inf. `dists`: the masks' distance transforms, if already made."""
    dists = dists or [mask_distance(m) for m in masks]
    out = np.empty(len(pts))
    for a in range(0, len(pts), chunk):
        sd = cone_distances(cameras, dists, pts[a : a + chunk])
        out[a : a + chunk] = _kth(sd, tolerance, nearest=True)
    return out


def carving_views(
    cameras: list[Camera],
    masks: list[np.ndarray],
    pts: np.ndarray,
    depth: float,
    carve: float = CARVE_MAX,
    chunk: int = 65536,
    dists: list[np.ndarray] | None = None,
) -> list[int]:
    """Views whose masks have holes. A ray through two parallel faces leaves parallel to how
    it came, shifted, and looks like air: a prism seen near its axis leaves a notch in its
    mask, and that view's cone cuts through the object. Each such view carves, by more than
    `depth` mm, more than `carve` of the core the views agree on (points deeper than `depth`
    inside the hull of all views but a fifth); a view with a sound mask carves none of it.
    On the quick protocol (80 views, 64^3 nodes over the object's box) this finds 8 of the
    prism's views and 4 of the vase's, and none of the other scenes' (measured with a
    since-removed study script; README, Fitting)."""
    dists = dists or [mask_distance(m) for m in masks]
    carved = np.zeros(len(cameras))
    core = 0
    for a in range(0, len(pts), chunk):
        sd = cone_distances(cameras, dists, pts[a : a + chunk])
        inner = _kth(sd, CORE_TOLERANCE) > depth
        core += int(inner.sum())
        carved += (sd[:, inner] < -depth).sum(axis=1)
    return [v for v in range(len(cameras)) if carved[v] > carve * max(core, 1)]


def visual_hull(
    box: Box,
    cameras: list[Camera],
    masks: list[np.ndarray],
    res: int,
    width: float = 0.0,
    tolerance: float = TOLERANCE,
    carve: float = CARVE_MAX,
) -> Hull:
    """Occupancy of a res^3 node grid over the box: a smooth step of the hull's signed
    distance across `width` mm (default: one cell), so that the surface is smooth. Views
    whose masks carve the others' core by more than `carve` are left out (`carving_views`;
    0 keeps every view)."""
    lo, hi = np.asarray(box.lo), np.asarray(box.hi)
    axes = [np.linspace(lo[a], hi[a], res) for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    cell = float(np.max((hi - lo) / (res - 1)))
    dists = [mask_distance(m) for m in masks]
    rejected = carving_views(cameras, masks, pts, cell, carve, dists=dists) if carve > 0 else []
    keep = sorted(set(range(len(cameras))) - set(rejected))
    sd = hull_distance(
        box,
        [cameras[v] for v in keep],
        [masks[v] for v in keep],
        pts,
        tolerance,
        dists=[dists[v] for v in keep],
    )
    # the box margin is air by construction; points behind every camera are air too, at a
    # finite distance: the flows and blurs of a hull take differences
    m = box.margin
    wall = np.min(np.minimum(pts - lo, hi - pts), axis=1) - 2 * m
    sd = np.clip(sd, -float(np.linalg.norm(hi - lo)), wall)
    w = width or cell
    frac = float(np.mean([mk.mean() for mk in masks])) if masks else 0.0
    return Hull(sd.reshape(res, res, res), w, frac, tuple(rejected))
