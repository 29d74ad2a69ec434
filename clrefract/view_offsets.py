"""Each training camera's centre, solved against a field: per view, the shift in its image
plane that minimises the photometric loss (the fit's sRGB residuals) over the pixels near the
object, by least squares on central differences of renders of those pixels, first on images
blurred by a pixel (a wider basin), then sharp. `dataset refine-positions` solves once
against a fitted field; a fit with fitted centres solves during the run (fit/centres.py).

The shift is sought in the image plane only (along the camera's right and up axes): moving
along the viewing direction scales the object by the shift over the distance (0.2 mm at
200 mm: 0.1%, a fortieth of a pixel at the rim of a 24-pixel sphere), which the photographs
hardly see, and a damped third component would stay at its prior anyway.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares

from .cameras import Camera, load_transforms
from .dataset import Dataset, holdout_split
from .envmap import EnvMap
from .loss import srgb
from .tracer import renders_black

GROW_PX = 3  # the object's pixels grown by this: a shift of up to MAX_SHIFT_PX stays inside
MAX_SHIFT_PX = 2.0  # bound of a shift, in pixel footprints at the object
STEP_PX = 0.25  # the central differences' half step, in pixel footprints
BLUR_PX = (1.0, 0.0)  # the rounds: Gaussian blur of render and photograph (pixels)
MAX_NFEV = 12  # least-squares iterations per round
MIN_PIXELS = 16  # fewer object pixels: the view is left as it is


@dataclass
class ViewOffset:
    """One training view's estimated camera shift."""

    frame: str  # "transforms_train.json: frames[k]"
    file_path: str
    offset_mm: np.ndarray  # (3,) world, added to the recorded camera centre
    right_up_mm: np.ndarray  # (2,) the same along the camera's right and up axes
    footprint_mm: float  # one pixel at the object
    loss_before: float  # mean squared sRGB residual over the object's pixels
    loss_after: float
    pixels: int
    at_bound: bool = False  # the shift reached MAX_SHIFT_PX: not trusted, not applied

    def to_dict(self) -> dict:
        return {
            "frame": self.frame,
            "file_path": self.file_path,
            "offset_mm": [round(float(x), 4) for x in self.offset_mm],
            "right_up_mm": [round(float(x), 4) for x in self.right_up_mm],
            "shift_px": round(float(np.linalg.norm(self.right_up_mm)) / self.footprint_mm, 3),
            "loss_before": round(self.loss_before, 7),
            "loss_after": round(self.loss_after, 7),
            "pixels": self.pixels,
            **({"at_bound": True} if self.at_bound else {}),
        }


def object_pixels(tracer, cam: Camera, image: np.ndarray, env: EnvMap, threshold: float):
    """(H, W) bool: the pixels the object can be seen in, recorded pose or shifted: the
    photograph's refraction mask and the pixels whose rays the field bends, grown by GROW_PX."""
    from .hull import refraction_mask

    o, d = cam.rays()
    bent = np.einsum("ij,ij->i", tracer.trace(o, d).direction, d) < 1 - 1e-9
    mask = refraction_mask(cam, image, env, threshold) | bent.reshape(cam.height, cam.width)
    return ndimage.binary_dilation(mask, iterations=GROW_PX)


class ViewProblem:
    """The residuals of one view as a function of its camera's shift (right, up; mm): the
    window of pixels around the object is traced, blurred as the round says, and compared
    with the photograph on the object's pixels."""

    def __init__(self, tracer, env, cam, image, weight, mask):
        self.tracer, self.env = tracer, env
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        pad = int(np.ceil(3 * max(BLUR_PX)))  # the blur's reach
        r0, r1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, cam.height)
        c0, c1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, cam.width)
        self.shape = (r1 - r0, c1 - c0)
        o, d = cam.rays()
        win = np.zeros((cam.height, cam.width), bool)
        win[r0:r1, c0:c1] = True
        self.o, self.d = o[win.ravel()], d[win.ravel()]
        self.image = image[r0:r1, c0:c1]
        self.mask = mask[r0:r1, c0:c1]
        self.weight = weight[r0:r1, c0:c1][self.mask][:, None]
        self.axes = cam.c2w[:3, :2]  # world right and up
        self.blur = 0.0
        self.target = self._encode(self.image)

    def set_blur(self, px: float) -> None:
        self.blur = px
        self.target = self._encode(self.image)

    def _encode(self, img: np.ndarray) -> np.ndarray:
        # blurred after the encoding: a bright light's radiance, blurred, floods its
        # neighbours (the encoding clips it at 1)
        enc = srgb(img)[0]
        if self.blur > 0:
            enc = ndimage.gaussian_filter(enc, (self.blur, self.blur, 0))
        return enc[self.mask]

    def render(self, x) -> np.ndarray:
        res = self.tracer.trace(self.o + self.axes @ np.asarray(x, float), self.d)
        rad = self.env.lookup(res.direction).astype(np.float64)
        rad[renders_black(res.status)] = 0.0
        return rad.reshape(*self.shape, 3)

    def residuals(self, x) -> np.ndarray:
        return ((self._encode(self.render(x)) - self.target) * self.weight).ravel()

    def jacobian(self, x, h: float) -> np.ndarray:
        cols = []
        for k in range(2):
            e = np.zeros(2)
            e[k] = h
            cols.append((self.residuals(x + e) - self.residuals(x - e)) / (2 * h))
        return np.stack(cols, axis=1)


def footprint_mm(cam: Camera, point) -> float:
    """The width of one pixel at `point` (mm)."""
    depth = float(-(np.asarray(point, float) - cam.position) @ cam.c2w[:3, 2])
    return abs(depth) / cam.fl_x


def estimate_offsets(
    ds: Dataset,
    tracer,
    views=None,
    threshold: float = 0.05,
    moved: np.ndarray | None = None,
    progress=None,
    env: EnvMap | None = None,
) -> list[ViewOffset]:
    """Per training view (all, or those of the indices `views` into ds.train), the shift of
    the camera's centre in its image plane that minimises the sRGB loss of the field `tracer`
    traces against the photograph, on the pixels near the object. `moved`: (len(ds.train),
    3) shifts the centres already have (the shifts found are from there); `progress`: called
    once a view; `env`: the panorama, where the caller holds it already (else read)."""
    env = ds.envmap() if env is None else env
    views = range(len(ds.train)) if views is None else views
    indices = train_indices(ds)
    centre = (np.asarray(ds.box.lo) + np.asarray(ds.box.hi)) / 2
    out = []
    for v in views:
        cam, k = ds.train[v], indices[v]
        image, weight = ds.frame(cam)
        if moved is not None:
            c2w = cam.c2w.copy()
            c2w[:3, 3] += moved[v]
            cam = replace(cam, c2w=c2w)
        if progress is not None:
            progress()
        image = image.astype(np.float64)
        mask = object_pixels(tracer, cam, image, env, threshold)
        foot = footprint_mm(cam, centre)
        frame = f"{ds.scene.train}: frames[{k}]"
        if mask.sum() < MIN_PIXELS:
            out.append(ViewOffset(frame, cam.file_path, np.zeros(3), np.zeros(2), foot, 0, 0, 0))
            continue
        prob = ViewProblem(tracer, env, cam, image, weight, mask)
        prob.set_blur(0.0)
        r0 = prob.residuals(np.zeros(2))
        bound = MAX_SHIFT_PX * foot
        x = np.zeros(2)
        for blur in BLUR_PX:
            prob.set_blur(blur)
            fit = least_squares(
                prob.residuals,
                x,
                jac=lambda x, p=prob, h=STEP_PX * foot: p.jacobian(x, h),
                bounds=(-bound, bound),
                x_scale=foot,
                max_nfev=MAX_NFEV,
                xtol=1e-3,
            )
            x = fit.x
        r1 = prob.residuals(x)
        at_bound = bool(np.any(np.abs(x) > 0.99 * bound))
        if at_bound or np.mean(r1**2) >= np.mean(r0**2):
            x, r1 = np.zeros(2), r0  # no better, or not trusted: left as recorded
        out.append(
            ViewOffset(
                frame,
                cam.file_path,
                prob.axes @ x,
                x,
                foot,
                float(np.mean(r0**2)),
                float(np.mean(r1**2)),
                int(mask.sum()),
                at_bound,
            )
        )
    return out


def train_indices(ds: Dataset) -> list[int]:
    """Each training camera's place among its transforms file's frames."""
    n = len(load_transforms(ds.root / ds.scene.train))
    if ds.scene.test != ds.scene.train:
        return list(range(n))
    return holdout_split(list(range(n)), ds.scene.holdout_every)[0]
