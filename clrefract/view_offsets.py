"""Each training camera's centre, solved against a field: per view, the shift in its image
plane that minimises the photometric loss (the fit's sRGB residuals) over the pixels near the
object, by least squares on central differences of renders of those pixels, first on images
blurred by a pixel (a wider basin), then sharp. `dataset refine-positions` solves once
against a fitted field; a fit with fitted centres solves during the run (fit/centres.py).

All views are solved in lockstep: each Levenberg-Marquardt iteration traces every unfinished
view's rays in one launch. One view's few thousand rays leave a device's lanes idle, and a
launch costs more than they do: view by view, the solve spent 18 ms a trace on 2,000 rays.

The shift is sought in the image plane only (along the camera's right and up axes): moving
along the viewing direction scales the object by the shift over the distance (0.2 mm at
200 mm: 0.1%, a fortieth of a pixel at the rim of a 24-pixel sphere), which the photographs
hardly see, and a damped third component would stay at its prior anyway.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from .cameras import Camera, load_transforms
from .dataset import Dataset, holdout_split
from .envmap import EnvMap
from .imageio import YCC
from .loss import srgb
from .tracer import renders_black

GROW_PX = 3  # the object's pixels grown by this: a shift of up to MAX_SHIFT_PX stays inside
MAX_SHIFT_PX = 2.0  # bound of a shift, in pixel footprints at the object
STEP_PX = 0.25  # the central differences' half step, in pixel footprints
BLUR_PX = (1.0, 0.0)  # the rounds: Gaussian blur of render and photograph (pixels), sharp last
MAX_NFEV = 12  # least-squares iterations per round
# a view has converged where its step is shorter than XTOL of its shift (as SciPy's xtol)
XTOL = 1e-3
PROBES = ((1, 0), (0, 1), (-1, 0), (0, -1))  # the central differences: +right, +up, -right, -up
DAMPING = 1e-3  # Levenberg-Marquardt's first damping, relative to the Gauss-Newton diagonal
MIN_PIXELS = 16  # fewer object pixels: the view is left as it is
LAUNCH_RAYS = 1 << 21  # the most rays of the views whose bent pixels one launch traces
PROGRESS_PER_VIEW = 1 + len(BLUR_PX)


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


def bent_pixels(tracer, cams: list) -> list:
    """Per camera, (H, W) bool: the pixels whose rays the field bends. The views are traced
    together, in launches of whole views of up to LAUNCH_RAYS rays."""
    sizes = [cam.width * cam.height for cam in cams]
    groups, count = [[]], 0
    for k, n in enumerate(sizes):
        if groups[-1] and count + n > LAUNCH_RAYS:
            groups.append([])
            count = 0
        groups[-1].append(k)
        count += n
    out = []
    for group in filter(None, groups):
        rays = [cams[k].rays() for k in group]
        d = np.concatenate([r[1] for r in rays])
        bent = np.einsum(
            "ij,ij->i", tracer.trace(np.concatenate([r[0] for r in rays]), d).direction, d
        )
        parts = np.split(bent < 1 - 1e-9, np.cumsum([sizes[k] for k in group])[:-1])
        out += [b.reshape(cams[k].height, cams[k].width) for k, b in zip(group, parts, strict=True)]
    return out


def object_pixels(cam: Camera, image: np.ndarray, bent: np.ndarray, env: EnvMap, threshold: float):
    """(H, W) bool: the pixels the object can be seen in, recorded pose or shifted: the
    photograph's refraction mask and the pixels whose rays the field bends (`bent`), grown
    by GROW_PX."""
    from .hull import refraction_mask

    mask = refraction_mask(cam, image, env, threshold) | bent
    return ndimage.binary_dilation(mask, iterations=GROW_PX)


class ViewProblem:
    """The residuals of one view as a function of its camera's shift (right, up; mm): the
    window of pixels around the object, blurred as the round says, compared with the
    photograph on the object's pixels. Only those are traced (`rays`): the mask is grown past
    the largest shift, so the rest of the window sees the panorama straight at any shift."""

    def __init__(self, cam, image, weight, mask, env: EnvMap, bound: float, foot: float,
                 space: str = "srgb"):  # fmt: skip
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        pad = int(np.ceil(3 * max(BLUR_PX)))  # the blur's reach
        self.blocks = space == "srgb420"  # colour per 2 x 2 block, as the file stored it
        r0, r1 = aligned(rows[0] - pad, rows[-1] + pad + 1, cam.height, self.blocks)
        c0, c1 = aligned(cols[0] - pad, cols[-1] + pad + 1, cam.width, self.blocks)
        self.shape = (r1 - r0, c1 - c0)
        o, d = cam.rays()
        win = np.zeros((cam.height, cam.width), bool)
        win[r0:r1, c0:c1] = True
        self.image = image[r0:r1, c0:c1]
        self.mask = mask[r0:r1, c0:c1]
        inside = self.mask.ravel()
        self.o, self.d = o[win.ravel()][inside], d[win.ravel()][inside]
        self.straight = env.lookup(d[win.ravel()]).astype(np.float64).reshape(*self.shape, 3)
        self.weight = weight[r0:r1, c0:c1][self.mask][:, None]
        self.axes = cam.c2w[:3, :2]  # world right and up
        self.bound, self.foot = bound, foot
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
        if self.blocks:  # the loss's srgb420: luma per pixel, chroma per block (loss.py)
            enc = enc @ YCC.T
            h, w = self.shape
            means = enc[:, :, 1:].reshape(h // 2, 2, w // 2, 2, 2).mean(axis=(1, 3))
            enc[:, :, 1:] = means.repeat(2, axis=0).repeat(2, axis=1)
        return enc[self.mask]

    def rays(self, x) -> tuple[np.ndarray, np.ndarray]:
        """The object's rays with the camera shifted by x."""
        return self.o + self.axes @ np.asarray(x, float), self.d

    def residuals(self, radiance: np.ndarray) -> np.ndarray:
        """The weighted sRGB residuals, given the object's rays' traced radiance."""
        img = self.straight.copy()
        img[self.mask] = radiance
        return ((self._encode(img) - self.target) * self.weight).ravel()


def aligned(lo: int, hi: int, size: int, blocks: bool) -> tuple[int, int]:
    """[lo, hi) clipped to [0, size); with blocks, grown to whole 2 x 2 blocks."""
    lo, hi = max(lo, 0), min(hi, size)
    if blocks:
        lo -= lo % 2
        hi = min(hi + (hi - lo) % 2, size - size % 2)
    return lo, hi


def radiance(tracer, env: EnvMap, problems: list, shifts: list) -> list:
    """Each problem's traced radiance with its camera shifted by the matching shift, all in
    one launch."""
    rays = [p.rays(x) for p, x in zip(problems, shifts, strict=True)]
    if not rays:
        return []
    res = tracer.trace(np.concatenate([o for o, _ in rays]), np.concatenate([d for _, d in rays]))
    rad = env.lookup(res.direction).astype(np.float64)
    rad[renders_black(res.status)] = 0.0
    return np.split(rad, np.cumsum([len(o) for o, _ in rays])[:-1])


def render(tracer, env: EnvMap, problems: list, shifts: list) -> list:
    """Each problem's residuals with its camera shifted by the matching shift."""
    rads = radiance(tracer, env, problems, shifts)
    return [p.residuals(r) for p, r in zip(problems, rads, strict=True)]


def solve_lockstep(tracer, env: EnvMap, problems: list, start: list, progress=None):
    """(len(problems), 2) shifts minimising each problem's squared residuals within its
    bound, and the residuals there in the last round: Levenberg-Marquardt on central
    differences (half step STEP_PX footprints), each step within a trust radius (a footprint
    or the shift so far at a round's start, twice a step that lowered the cost, a quarter of
    one that did not), the views that have not converged stepping together, over the
    rounds of BLUR_PX, from no shift, whose radiance is `start`. The radius: a
    Gauss-Newton step against a crude field can leap to the bound, where the view is not
    trusted. `progress`: called with the count of views each iteration finishes for its round."""
    progress = progress or (lambda n: None)
    x = np.zeros((len(problems), 2))
    for k, blur in enumerate(BLUR_PX):
        for p in problems:
            p.set_blur(blur)
        if k == 0:
            r = [p.residuals(s) for p, s in zip(problems, start, strict=True)]
        else:
            r = render(tracer, env, problems, list(x))
        cost = np.array([float(v @ v) for v in r])
        damping = np.full(len(problems), DAMPING)
        radius = np.maximum(np.linalg.norm(x, axis=1) / np.array([p.foot for p in problems]), 1.0)
        normal = {}  # each view's Gauss-Newton system at its x: kept until x moves
        live = list(range(len(problems)))
        for _ in range(MAX_NFEV):
            stale = [i for i in live if i not in normal]
            probe = [(i, x[i] + STEP_PX * problems[i].foot * np.array(e)) for i in stale
                     for e in PROBES]  # fmt: skip
            out = render(tracer, env, [problems[i] for i, _ in probe], [v for _, v in probe])
            for n, i in enumerate(stale):
                d = np.array(out[4 * n : 4 * n + 2]) - np.array(out[4 * n + 2 : 4 * n + 4])
                jac = d.T / (2 * STEP_PX * problems[i].foot)
                normal[i] = (jac.T @ jac, jac.T @ r[i])
            trial = {}
            for i in live:
                a, g = normal[i]
                step = np.linalg.solve(a + damping[i] * np.diag(np.maximum(np.diag(a), 1e-300)), -g)
                step *= min(1.0, radius[i] * problems[i].foot / max(np.linalg.norm(step), 1e-300))
                trial[i] = np.clip(x[i] + step, -problems[i].bound, problems[i].bound)
            out = render(tracer, env, [problems[i] for i in live], [trial[i] for i in live])
            still = []
            for i, ri in zip(live, out, strict=True):
                moved = float(np.linalg.norm(trial[i] - x[i]))
                if float(ri @ ri) < cost[i]:
                    x[i], r[i], cost[i] = trial[i], ri, float(ri @ ri)
                    damping[i] /= 3
                    radius[i] = max(radius[i], 2 * moved / problems[i].foot)
                    del normal[i]
                else:
                    damping[i] *= 4
                    radius[i] = moved / problems[i].foot / 4
                if moved >= XTOL * (XTOL * problems[i].foot + float(np.linalg.norm(x[i]))):
                    still.append(i)
            progress(len(live) - len(still))
            live = still
            if not live:
                break
        progress(len(live))
    return x, r


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
    space: str = "srgb",
) -> list[ViewOffset]:
    """Per training view (all, or those of the indices `views` into ds.train), the shift of
    the camera's centre in its image plane that minimises the sRGB loss of the field `tracer`
    traces against the photograph, on the pixels near the object.
    moved: (len(ds.train), 3) shifts the centres already have (the shifts found are from
    there); progress: called with counts, PROGRESS_PER_VIEW in all for each view (its
    set-up, then each round); env: the panorama, where the caller holds it already (else
    read); space: the fit's loss space (srgb420: the frames' colour compared per
    2 x 2 block, as ds reads it with train_chroma "stored"; any other: sRGB per pixel)."""
    env = ds.envmap() if env is None else env
    views = range(len(ds.train)) if views is None else views
    progress = progress or (lambda n=1: None)
    indices = train_indices(ds)
    centre = (np.asarray(ds.box.lo) + np.asarray(ds.box.hi)) / 2
    cams, frames = [], []
    for v in views:
        cam = ds.train[v]
        if moved is not None:
            c2w = cam.c2w.copy()
            c2w[:3, 3] += moved[v]
            cam = replace(cam, c2w=c2w)
        cams.append(cam)
        frames.append(ds.frame(ds.train[v]))
        progress()
    out, problems = [], {}
    bent = bent_pixels(tracer, cams)
    for n, (v, cam, (image, weight)) in enumerate(zip(views, cams, frames, strict=True)):
        k = indices[v]
        image = image.astype(np.float64)
        mask = object_pixels(cam, image, bent[n], env, threshold)
        foot = footprint_mm(cam, centre)
        out.append(ViewOffset(f"{ds.scene.train}: frames[{k}]", cam.file_path, np.zeros(3),
                              np.zeros(2), foot, 0, 0, 0))  # fmt: skip
        if mask.sum() < MIN_PIXELS:
            progress(len(BLUR_PX))  # no rounds to solve
        else:
            problems[n] = ViewProblem(
                cam, image, weight, mask, env, MAX_SHIFT_PX * foot, foot, space
            )
    probs = list(problems.values())
    unshifted = radiance(tracer, env, probs, [np.zeros(2)] * len(probs))
    before = [p.residuals(r) for p, r in zip(probs, unshifted, strict=True)]  # sharp
    shifts, after = solve_lockstep(tracer, env, probs, unshifted, progress)  # the sharp round's
    for n, p, x, r0, r1 in zip(problems, probs, shifts, before, after, strict=True):
        at_bound = bool(np.any(np.abs(x) > 0.99 * p.bound))
        if at_bound or np.mean(r1**2) >= np.mean(r0**2):
            x, r1 = np.zeros(2), r0  # no better, or not trusted: left as recorded
        out[n] = replace(out[n], offset_mm=p.axes @ x, right_up_mm=x,
                         loss_before=float(np.mean(r0**2)), loss_after=float(np.mean(r1**2)),
                         pixels=int(p.mask.sum()), at_bound=at_bound)  # fmt: skip
    return out


def train_indices(ds: Dataset) -> list[int]:
    """Each training camera's place among its transforms file's frames."""
    n = len(load_transforms(ds.root / ds.scene.train))
    if ds.scene.test != ds.scene.train:
        return list(range(n))
    return holdout_split(list(range(n)), ds.scene.holdout_every)[0]
