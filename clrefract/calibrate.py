"""`clrefract dataset register-env`: the panorama's orientation, and each view's exposure and
white balance, from the background pixels: those whose camera rays miss the object's box
and so see the panorama straight (their value is env.lookup(ray direction), up to the
frame's exposure and white balance).

The orientation is found on log radiance with each view's RGB gain taken out (the median
log ratio, per view and channel), under a soft-L1 loss: first a grid over the yaw and small
tilts against a blurred panorama, then Nelder-Mead from the best few, blurred then sharp.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares, minimize

from .cameras import Camera
from .dataset import SCENE_FILE, Dataset
from .envmap import EnvMap, pixel_directions, rotation_matrix
from .errors import ClrefractError
from .fields.base import Box
from .imageio import atomic_path
from .log import logger

MIN_VIEW_PIXELS = 32  # fewer background pixels than this: the view's gain is left as it is
LOG_SCALE = 0.1  # soft-L1 scale of log residuals: a tenth of a stop is "inlier" noise
GRID_YAW_STEP = 3.0  # degrees; the coarse grid's spacing about z
GRID_TILTS = (-12.0, -6.0, 0.0, 6.0, 12.0)  # degrees about x and about y
COARSE_BLUR_DEG = 3.0  # the blurred panorama of the grid: half its tilt spacing
COARSE_WIDTH = 240  # pixels across the grid's panorama: 1.5 degrees each, finer than its blur
MEDIUM_BLUR_DEG = 1.0
COARSE_PIXELS = 1_500  # samples over all views: grid and blurred refinement
FINE_PIXELS = 16_000  # samples over all views: the sharp refinement
N_STARTS = 3  # grid minima refined
POOR_MATCH = 0.3  # RMS log residual above which the match is reported as poor
# a dataset as stated, above which it needs registering: clrefract's own clean datasets sit
# at 0.006 and 1e-4 (a pixel's footprint), a rendered capture with sensor noise and JPEG at
# 0.08 once registered; its panorama turned by 5 degrees and its exposures jittered by
# 0.3 EV read 0.14 and 0.39
MISMATCH_RESIDUAL = 0.05
MISMATCH_GAIN_LOG = 0.05  # 5% in any channel of any view
# a view's camera turned by a tenth of a degree (half a pixel at 128 x 128) took a clean
# sphere's fit from 58.98 dB to 31.6 unregistered; clean datasets read below 0.005
MISMATCH_TURN_DEG = 0.03
TURN_PROBE_DEG = 0.05  # the central differences' turn
# where the box leaves few rays that miss it (the default box, the region the cameras look
# at, often fills the views), every pixel is used and the object's are trimmed after a first,
# robust registration: refracted pixels see the panorama elsewhere, far beyond a third of a
# stop
MIN_SHARE = 0.05  # of all pixels: fewer past the box, and every pixel is used
TRIM_LOG = 0.25
VIEW_PIXELS = 3_000  # samples of a view's background that fix its rotation


@dataclass
class View:
    """One frame's background pixels: world directions and the linear values as the dataset
    reads them (times its current exposure and white balance)."""

    source: Path  # its transforms file
    index: int  # its place in that file's frames
    camera: Camera
    dirs: np.ndarray  # (n, 3)
    rgb: np.ndarray  # (n, 3), all positive


@dataclass
class Registration:
    angles: np.ndarray  # [rx, ry, rz] degrees, scene.json's envmap_rotation
    residual: float  # RMS log residual, gains taken out
    residual_before: float  # the same at the scene's rotation (or none)
    starts: list = field(default_factory=list)  # (angles, loss) of each refined start


def background_views(ds: Dataset, box: Box | None = None, whole: bool = False) -> list[View]:
    """The background pixels of every frame of a dataset (both splits, each frame once): rays
    that miss the box grown by its margin (whole: every ray), not clipped, positive in every
    channel."""
    box = box or ds.box
    lo = np.asarray(box.lo, float) - box.margin
    hi = np.asarray(box.hi, float) + box.margin
    grown = Box(tuple(lo), tuple(hi), box.margin)
    views = []
    for source, k, cam in ds.frames():
        o, d = cam.rays()
        near, far = grown.ray_span(o, d)
        miss = (far <= near) | (far <= 0) | whole
        img, weight = ds.frame(cam)
        rgb = img.reshape(-1, 3).astype(np.float64)
        keep = miss & (weight.ravel() > 0) & (rgb > 0).all(axis=1)
        views.append(View(source, k, cam, d[keep], rgb[keep]))
    return views


def inliers(env: EnvMap, views: list[View], angles) -> list[View]:
    """The pixels of each view that the panorama turned by `angles` explains to within
    TRIM_LOG (each view's RGB gain taken out): the background, where the object is unknown."""
    floor = _floor(env)
    m = rotation_matrix(np.asarray(angles, float))
    out = []
    for v in views:
        r = np.log(v.rgb) - log_lookup(env, v.dirs @ m, floor)
        r -= np.median(r, axis=0)
        keep = np.abs(r).max(axis=1) < TRIM_LOG
        out.append(View(v.source, v.index, v.camera, v.dirs[keep], v.rgb[keep]))
    return out


class NoBackground(ClrefractError):
    """No pixel of any view sees the panorama straight."""


def no_background_error(ds: Dataset, box: Box) -> ClrefractError:
    where = ds.root / SCENE_FILE if (ds.root / SCENE_FILE).is_file() else ds.root
    return NoBackground(
        f"{where}: no background pixels: every camera ray meets the box "
        f"{list(box.lo)}..{list(box.hi)} mm, so no pixel sees the panorama straight "
        "(give a smaller --box that still holds the object)"
    )


def log_lookup(env: EnvMap, dirs: np.ndarray, floor: float) -> np.ndarray:
    """Log radiance of the panorama along world directions (n, 3), clamped at `floor`."""
    return np.log(np.maximum(env.lookup(dirs), floor))


def _floor(env: EnvMap) -> float:
    """Radiance below which logs are clamped: black panorama pixels stay finite."""
    return 1e-4 * max(float(np.median(env.image)), 1e-12)


class _Samples:
    """An equal number of background pixels of each view, as (V, n, 3) arrays, so that each
    view's median log ratio is one NumPy call."""

    def __init__(self, views: list[View], total: int, rng: np.random.Generator):
        n = int(np.clip(total // max(len(views), 1), 32, 2048))
        dirs, logs = [], []
        for v in views:
            pick = rng.choice(len(v.dirs), n, replace=len(v.dirs) < n)
            dirs.append(v.dirs[pick])
            logs.append(np.log(v.rgb[pick]))
        self.dirs = np.stack(dirs)
        self.logs = np.stack(logs)

    def residuals(self, env: EnvMap, angles, floor: float) -> np.ndarray:
        """Log residuals (V, n, 3) with each view's RGB gain (median log ratio) taken out."""
        m = rotation_matrix(np.asarray(angles, float))
        e = log_lookup(env, self.dirs.reshape(-1, 3) @ m, floor).reshape(self.logs.shape)
        r = self.logs - e
        return r - np.median(r, axis=1, keepdims=True)

    def loss(self, env: EnvMap, angles, floor: float) -> float:
        return float(_soft_l1(self.residuals(env, angles, floor)).mean())

    def yaw_losses(self, env: EnvMap, tilt: np.ndarray, yaws: np.ndarray, floor: float):
        """The loss of every rotation tilt @ Rz(yaw) (yaws in degrees), at once: a turn
        about the panorama's own axis shifts its columns, so each sample's row of the map is
        interpolated once and then only shifted (env.lookup's bilinear conventions)."""
        u = self.dirs.reshape(-1, 3) @ tilt
        h, w = env.height, env.width
        row = np.arccos(np.clip(u[:, 2], -1.0, 1.0)) / np.pi * h - 0.5
        r0 = np.floor(row)
        fr = (row - r0)[:, None, None].astype(np.float32)
        r0 = r0.astype(np.int64)
        img = env.image
        ring = img[np.clip(r0, 0, h - 1)] * (1 - fr) + img[np.clip(r0 + 1, 0, h - 1)] * fr
        col = (0.5 + np.arctan2(u[:, 1], u[:, 0]) / (2 * np.pi)) * w - 0.5
        col = col[:, None] - np.asarray(yaws) / 360.0 * w  # (P, Y)
        c0 = np.floor(col)
        fc = (col - c0)[..., None].astype(np.float32)
        c0 = np.mod(c0.astype(np.int64), w)
        e = np.take_along_axis(ring, c0[..., None], 1) * (1 - fc)
        e += np.take_along_axis(ring, np.mod(c0 + 1, w)[..., None], 1) * fc
        v, n = self.logs.shape[:2]
        r = self.logs.reshape(-1, 1, 3) - np.log(np.maximum(e, floor))
        r = r.reshape(v, n, len(yaws), 3)
        r -= np.median(r, axis=1, keepdims=True)
        return _soft_l1(r).mean(axis=(0, 1, 3))

    def rms(self, env: EnvMap, angles, floor: float) -> float:
        return float(np.sqrt(np.mean(self.residuals(env, angles, floor) ** 2)))


def _soft_l1(r: np.ndarray) -> np.ndarray:
    z = r / LOG_SCALE
    return np.sqrt(1.0 + z * z) - 1.0


def wrap_degrees(angles) -> np.ndarray:
    """Angles in (-180, 180]."""
    a = np.mod(np.asarray(angles, float) + 180.0, 360.0) - 180.0
    return np.where(a == -180.0, 180.0, a)


def rotation_angle(a, b) -> float:
    """Degrees between two envmap_rotation values (angles or matrices)."""
    m = rotation_matrix(a).T @ rotation_matrix(b)
    return math.degrees(math.acos(float(np.clip((np.trace(m) - 1) / 2, -1.0, 1.0))))


def _blur(env: EnvMap, degrees: float) -> EnvMap:
    return env.blurred(degrees / 360.0 * env.width)


def _refine(samples: _Samples, env: EnvMap, start, step: float, floor: float, tol: float):
    simplex = np.asarray(start, float) + np.vstack([np.zeros(3), np.eye(3) * step])
    res = minimize(
        lambda a: samples.loss(env, a, floor),
        start,
        method="Nelder-Mead",
        options={"initial_simplex": simplex, "xatol": tol, "fatol": 1e-9, "maxiter": 600},
    )
    return res.x, float(res.fun)


def log_residual(env: EnvMap, views: list[View], angles, seed: int = 0) -> float:
    """RMS log residual of the views' background pixels against the panorama (in its own
    frame) turned by `angles`, each view's RGB gain taken out."""
    fine = _Samples(views, FINE_PIXELS, np.random.default_rng(seed))
    return fine.rms(env, angles, _floor(env))


def grid_starts(samples: _Samples, env: EnvMap, floor: float) -> list[np.ndarray]:
    """The N_STARTS best rotations of a grid over the yaw and small tilts, against the
    panorama blurred by COARSE_BLUR_DEG, each apart from the others."""
    blurred = _blur(env, COARSE_BLUR_DEG)
    small = pixel_directions(COARSE_WIDTH, COARSE_WIDTH // 2).reshape(-1, 3)
    small = EnvMap(blurred.lookup(small).reshape(COARSE_WIDTH // 2, COARSE_WIDTH, 3))
    yaws = np.arange(-180.0, 180.0, GRID_YAW_STEP)
    grid, losses = [], []
    for ry in GRID_TILTS:
        for rx in GRID_TILTS:
            tilt = rotation_matrix([rx, ry, 0.0])
            losses.append(samples.yaw_losses(small, tilt, yaws, floor))
            grid += [tilt @ rotation_matrix([0.0, 0.0, yaw]) for yaw in yaws]
    picked: list[np.ndarray] = []
    for i in np.argsort(np.concatenate(losses)):  # the best few, apart from each other
        g = angles_of(grid[i])
        if all(rotation_angle(g, p) > 2 * GRID_YAW_STEP for p in picked):
            picked.append(g)
        if len(picked) == N_STARTS:
            break
    return picked


def register_rotation(env: EnvMap, views: list[View], starts=(), seed: int = 0) -> Registration:
    """The panorama's rotation (scene.json's envmap_rotation, degrees) that best matches the
    views' background pixels. `env` is the panorama in its own frame; `starts` are rotations
    to refine besides the grid's best (the scene's own, say)."""
    rng = np.random.default_rng(seed)
    floor = _floor(env)
    coarse = _Samples(views, COARSE_PIXELS, rng)
    fine = _Samples(views, FINE_PIXELS, rng)
    starts = [np.asarray(s, float) for s in starts]
    before = starts[0] if starts else np.zeros(3)
    starts += grid_starts(coarse, env, floor)
    env_m = _blur(env, MEDIUM_BLUR_DEG)
    refined = [_refine(coarse, env_m, s, COARSE_BLUR_DEG, floor, 0.05) for s in starts]
    best, _ = min(refined, key=lambda t: t[1])
    best = wrap_degrees(_refine(fine, env, best, 0.5, floor, 1e-3)[0])
    return Registration(
        angles=best,
        residual=fine.rms(env, best, floor),
        residual_before=fine.rms(env, before, floor),
        starts=[(wrap_degrees(a).tolist(), loss) for a, loss in refined],
    )


def rotvec_matrix(w) -> np.ndarray:
    """The rotation by the vector w (radians): its axis and angle."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(w, float)).as_matrix()


def refine_view_rotations(env: EnvMap, views: list[View], angles, seed: int = 0) -> list:
    """Per view, the small turn (3 x 3, world frame, about the camera's centre) that takes its
    background pixels onto the panorama turned by `angles`: a camera's rotation is fixed by
    the panorama at infinity, to a fraction of a pixel, where its pose was off (its position
    is not: nothing at infinity moves with it). None for a view with too few pixels."""
    floor = _floor(env)
    m = rotation_matrix(np.asarray(angles, float))
    rng = np.random.default_rng(seed)
    coarse = _blur(env, MEDIUM_BLUR_DEG)
    out = []
    for v in views:
        if len(v.dirs) < MIN_VIEW_PIXELS:
            out.append(None)
            continue
        pick = rng.choice(len(v.dirs), min(len(v.dirs), VIEW_PIXELS), replace=False)
        d, logs = v.dirs[pick], np.log(v.rgb[pick])

        def residual(w, e, d=d, logs=logs):
            r = logs - log_lookup(e, d @ rotvec_matrix(w).T @ m, floor)
            return (r - np.median(r, axis=0)).ravel()

        w = np.zeros(3)
        for e in (coarse, env):
            w = least_squares(
                residual, w, args=(e,), loss="soft_l1", f_scale=LOG_SCALE, diff_step=1e-4
            ).x
        out.append(rotvec_matrix(w))
    return out


def estimate_gains(env: EnvMap, angles, views: list[View]) -> list[np.ndarray | None]:
    """Per view, the RGB factor (3,) that takes its values (as read) onto the panorama rotated
    by `angles`: a soft-L1 fit of the log ratio; None for a view with too few background
    pixels."""
    floor = _floor(env)
    m = rotation_matrix(np.asarray(angles, float))
    out: list[np.ndarray | None] = []
    for v in views:
        if len(v.dirs) < MIN_VIEW_PIXELS:
            out.append(None)
            continue
        r = log_lookup(env, v.dirs @ m, floor) - np.log(v.rgb)
        out.append(np.exp([_location(r[:, c]) for c in range(3)]))
    return out


def _location(r: np.ndarray) -> float:
    """A soft-L1 estimate of the centre of r (log ratios), from its median."""
    fit = least_squares(lambda x: r - x[0], [np.median(r)], loss="soft_l1", f_scale=LOG_SCALE / 2)
    return float(fit.x[0])


def split_gain(gain) -> tuple[float, list[float]]:
    """exposure_scale (the geometric mean) and white_balance (geometric mean 1) of an RGB gain."""
    gain = np.asarray(gain, float)
    exposure = float(np.exp(np.mean(np.log(gain))))
    return exposure, (gain / exposure).tolist()


def read_json(path: Path) -> dict:
    """A JSON object from a file; ClrefractError naming it if unreadable or not an object."""
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ClrefractError(f"{path}: cannot read ({exc})") from None
    if not isinstance(d, dict):
        raise ClrefractError(f"{path}: top level must be a JSON object")
    return d


def write_json(path: Path, d: dict) -> None:
    """Write a JSON object whole or not at all (indented, as the transforms files are)."""
    with atomic_path(path, suffix=".json") as tmp:
        tmp.write_text(json.dumps(d, indent=2) + "\n", encoding="utf-8")


@dataclass
class Corrections:
    """What a registration changes in a dataset: the panorama's rotation (None: kept), and per
    frame, keyed by (transforms file name, place in its frames), the exposure_scale and
    white_balance found and the turn (3 x 3, world frame) that puts its camera onto the
    panorama. Applied in memory (`apply`), kept in a run folder (`to_dict`), or written into
    the dataset's files (`write`)."""

    envmap_rotation: list | None = None
    gains: dict = field(default_factory=dict)  # (file, index) -> (exposure, [r, g, b])
    turns: dict = field(default_factory=dict)  # (file, index) -> 3 x 3 array

    def apply(self, ds: Dataset) -> None:
        """Change `ds`'s scene and cameras in memory, as written files would read."""
        if self.envmap_rotation is not None:
            ds.scene.envmap_rotation = list(self.envmap_rotation)
        for source, k, cam in ds.frames():
            key = (source.name, k)
            if key in self.turns:
                cam.c2w[:3, :3] = np.asarray(self.turns[key]) @ cam.c2w[:3, :3]
            if key in self.gains:
                cam.exposure, wb = self.gains[key]
                cam.white_balance = tuple(float(x) for x in wb)

    def write(self, root: Path) -> list[str]:
        """Store them in a dataset folder's scene.json and transforms files, keeping every
        other key; the files written."""
        root = Path(root)
        edits: dict[str, dict] = {}
        for name, _ in [*self.turns, *self.gains]:
            edits.setdefault(name, read_json(root / name))
        for (name, k), t in self.turns.items():
            fr = edits[name]["frames"][k]
            c2w = np.asarray(fr["transform_matrix"], float)
            c2w[:3, :3] = np.asarray(t) @ c2w[:3, :3]
            fr["transform_matrix"] = c2w.tolist()
        for (name, k), (e, wb) in self.gains.items():
            fr = edits[name]["frames"][k]
            fr["exposure_scale"] = round(e, 6)
            fr["white_balance"] = [round(x, 6) for x in wb]
        written = []
        for name, d in edits.items():
            write_json(root / name, d)
            written.append(str(root / name))
        if self.envmap_rotation is not None:
            scene_path = root / SCENE_FILE
            scene = read_json(scene_path) if scene_path.is_file() else {}
            scene["envmap_rotation"] = list(self.envmap_rotation)
            write_json(scene_path, scene)
            written.append(str(scene_path))
        return written

    def to_dict(self) -> dict:
        frames = {}
        for (name, k), t in self.turns.items():
            frames.setdefault((name, k), {})["turn"] = np.round(t, 12).tolist()
        for (name, k), (e, wb) in self.gains.items():
            frames.setdefault((name, k), {}).update(
                exposure_scale=round(e, 6), white_balance=[round(x, 6) for x in wb]
            )
        return {
            "envmap_rotation": self.envmap_rotation,
            "frames": [{"file": n, "index": k, **v} for (n, k), v in sorted(frames.items())],
        }

    @classmethod
    def from_dict(cls, d: dict, where: Path) -> Corrections:
        try:
            out = cls(d.get("envmap_rotation"))
            for fr in d["frames"]:
                key = (str(fr["file"]), int(fr["index"]))
                if "turn" in fr:
                    out.turns[key] = np.asarray(fr["turn"], float).reshape(3, 3)
                if "exposure_scale" in fr:
                    wb = [float(x) for x in fr["white_balance"]]
                    out.gains[key] = (float(fr["exposure_scale"]), wb)
        except (KeyError, TypeError, ValueError) as exc:
            raise ClrefractError(f"{where}: not a registration ({exc!r})") from None
        return out


@dataclass
class Mismatch:
    """How far a dataset's background pixels are from its panorama as the dataset states it,
    without searching: the RMS log residual with each view's RGB gain taken out (a turned
    panorama or turned cameras), the largest gain a view needs (exposure and white balance),
    as |log|, and the median turn (degrees) that takes a view's camera onto the panorama, to
    first order."""

    residual: float
    gain_log: float
    turn_deg: float

    def needs_registration(self) -> bool:
        return (
            self.residual > MISMATCH_RESIDUAL
            or self.gain_log > MISMATCH_GAIN_LOG
            or self.turn_deg > MISMATCH_TURN_DEG
        )

    def words(self) -> str:
        return (
            f"RMS log residual {self.residual:.3f}, exposure or white balance off by up to "
            f"{100 * (math.exp(self.gain_log) - 1):.0f}%, cameras turned by about "
            f"{self.turn_deg:.2f} degrees"
        )


def linear_view_turns(env: EnvMap, views: list[View], angles, seed: int = 0) -> list[float]:
    """Per view with enough pixels, the turn (degrees) of refine_view_rotations to first
    order: least squares of its log residuals on their derivatives along turns about the three
    axes (central differences); pixels the panorama does not explain to TRIM_LOG are left out."""
    floor = _floor(env)
    m = rotation_matrix(np.asarray(angles, float))
    rng = np.random.default_rng(seed)
    eps = math.radians(TURN_PROBE_DEG)
    out = []
    for v in _enough(views):
        pick = rng.choice(len(v.dirs), min(len(v.dirs), VIEW_PIXELS), replace=False)
        d, logs = v.dirs[pick], np.log(v.rgb[pick])

        def look(w, d=d):
            return log_lookup(env, d @ rotvec_matrix(w).T @ m, floor)

        r = logs - look(np.zeros(3))
        r -= np.median(r, axis=0)
        cols = [(look(eps * e) - look(-eps * e)) / (2 * eps) for e in np.eye(3)]
        keep = np.abs(r).max(axis=1) < TRIM_LOG
        jac = np.stack([c[keep].ravel() for c in cols], axis=1)
        w = np.linalg.lstsq(jac, r[keep].ravel(), rcond=None)[0]
        out.append(math.degrees(float(np.linalg.norm(w))))
    return out


def _enough(views: list[View]) -> list[View]:
    return [v for v in views if len(v.dirs) >= MIN_VIEW_PIXELS]


def _background(ds: Dataset, given: bool) -> tuple[list[View], bool]:
    """Every frame's background pixels: those past the box, or every pixel (then True: the
    object's are to be trimmed) where the box leaves too few and was not the user's."""
    views = background_views(ds, ds.box)
    total = sum(v.camera.width * v.camera.height for v in views)
    if sum(len(v.dirs) for v in _enough(views)) < MIN_SHARE * total and not given:
        return background_views(ds, ds.box, whole=True), True
    return views, False


def _seen(ds: Dataset, views: list[View]) -> list[View]:
    seen = _enough(views)
    if not seen:
        raise no_background_error(ds, ds.box)
    return seen


def mismatch(ds: Dataset, given: bool = False, seed: int = 0) -> Mismatch:
    """The background against the panorama at the scene's rotation and the frames' gains
    (`given`: as `register`'s)."""
    env = EnvMap.from_file(ds.root / ds.scene.envmap)
    old = ds.scene.envmap_rotation
    angles = np.zeros(3) if old is None else angles_of(old)
    views, whole = _background(ds, given)
    seen = _seen(ds, inliers(env, views, angles) if whole else views)
    gains = [g for g in estimate_gains(env, angles, seen) if g is not None]
    worst = float(np.abs(np.log(gains)).max()) if gains else 0.0
    turn = float(np.median(linear_view_turns(env, seen, angles, seed)))
    return Mismatch(log_residual(env, seen, angles, seed), worst, turn)


def describe_background(root: Path, box: Box | None, notes: list[str]) -> None:
    """Warn where the background pixels differ from the panorama as the dataset states it
    (its rotation, the frames' exposures), with what registers it."""
    try:
        found = mismatch(Dataset(root, box=box), given=box is not None)
    except NoBackground as exc:  # said, not a problem
        notes.append(f"the panorama is not checked against the photographs: {exc}")
        return
    if found.needs_registration():
        notes.append(
            f"warning: the background differs from the panorama as stated ({found.words()}): "
            "`clrefract fit` registers it before its start (--register auto), and "
            f"`clrefract dataset register-env --exposure --poses --write {root}` stores it"
        )


def register(
    ds: Dataset,
    exposure: bool = False,
    given: bool = False,
    keep_rotation: bool = False,
    seed: int = 0,
    poses: bool = False,
) -> tuple[dict, Corrections]:
    """Register a dataset's panorama (unless keep_rotation); with `poses`, turn each camera
    onto it; with `exposure`, estimate each view's exposure_scale and white_balance. `given`:
    whether ds's box was the user's (then only the pixels past it are used). What it found
    (a JSON-able dict) and the corrections, not yet applied."""
    views, whole = _background(ds, given)
    seen = _seen(ds, views)
    env = EnvMap.from_file(ds.root / ds.scene.envmap)  # its own frame: the rotation is sought
    old = ds.scene.envmap_rotation
    starts = [] if old is None else [angles_of(old)]
    if keep_rotation:
        angles = starts[0] if starts else np.zeros(3)
    else:
        angles = register_rotation(env, seen, starts, seed=seed).angles
    if whole:
        views = inliers(env, views, angles)
        seen = _seen(ds, views)
    if keep_rotation:
        rms = log_residual(env, seen, angles, seed)
        reg = Registration(angles, rms, rms)
    else:
        # the first start is what the residual "before" is measured at
        reg = register_rotation(env, seen, [*(starts or [np.zeros(3)]), angles], seed=seed)
        angles = np.round(reg.angles, 4)
    out = Corrections(None if keep_rotation else angles.tolist())
    info: dict = {
        "dataset": str(ds.root),
        "envmap_rotation": np.round(angles, 4).tolist(),
        "residual_log_rms": round(reg.residual, 5),
        "residual_log_rms_before": round(reg.residual_before, 5),
        "turned_deg": round(rotation_angle(starts[0] if starts else np.zeros(3), angles), 4),
        "views": len(views),
        "pixels": "background past the box" if not whole else "every pixel, the object's trimmed",
        "background_pixels": int(sum(len(v.dirs) for v in views)),
        "views_without_background": [
            f"{v.source.name}: frames[{v.index}]" for v in views if len(v.dirs) < MIN_VIEW_PIXELS
        ],
    }
    turns = refine_view_rotations(env, views, angles, seed) if poses else []
    if poses:
        info["view_turns_deg"] = [
            None if t is None else round(rotation_angle(np.eye(3), t), 4) for t in turns
        ]
        out.turns = {(v.source.name, v.index): t for v, t in zip(views, turns) if t is not None}
        views = [
            v if t is None else View(v.source, v.index, v.camera, v.dirs @ t.T, v.rgb)
            for v, t in zip(views, turns, strict=True)
        ]
    if exposure:
        info["frames"] = []
        for v, g in zip(views, estimate_gains(env, angles, views), strict=True):
            if g is None:
                continue
            now = v.camera.exposure * np.asarray(v.camera.white_balance)
            e, wb = split_gain(now * g)
            out.gains[(v.source.name, v.index)] = (e, wb)
            info["frames"].append(
                {
                    "frame": f"{v.source.name}: frames[{v.index}]",
                    "file_path": v.camera.file_path,
                    "exposure_scale": round(e, 6),
                    "white_balance": [round(x, 6) for x in wb],
                }
            )
    logger.info(
        f"{ds.root}: panorama rotation {np.round(angles, 4).tolist()} degrees, RMS log "
        f"residual {reg.residual:.4f} (before {reg.residual_before:.4f})"
    )
    if reg.residual > POOR_MATCH:
        logger.warning(
            f"{ds.root}: the background pixels match the panorama poorly (RMS log residual "
            f"{reg.residual:.2f}): is it the right panorama, and does the box hold the object?"
        )
    return info, out


def calibrate(
    root,
    exposure: bool = False,
    write: bool = False,
    box: Box | None = None,
    keep_rotation: bool = False,
    seed: int = 0,
    poses: bool = False,
) -> dict:
    """`dataset register-env`: `register` a dataset folder (`box`: the user's); with `write`,
    store what it found in its files (scene.json's envmap_rotation, the transforms files'
    frames), keeping every other key. What it found, as a JSON-able dict."""
    ds = Dataset(root, box=box)
    info, found = register(ds, exposure, box is not None, keep_rotation, seed, poses)
    info["written"] = found.write(ds.root) if write else []
    return info


REGISTRATION_FILE = "registration.json"  # a run folder's Corrections (`fit --register`)
# where a fit that moved its training cameras with the field says how far (fit/centres.py)
CENTRES_FILE = "camera_centres.json"


def run_corrections(run) -> Corrections | None:
    """The registration a fit made and kept in its run folder, None without one."""
    path = Path(run) / REGISTRATION_FILE
    return Corrections.from_dict(read_json(path), path) if path.is_file() else None


def angles_of(value) -> np.ndarray:
    """[rx, ry, rz] degrees (R = Rz Ry Rx) of an envmap_rotation value, angles or a matrix."""
    m = rotation_matrix(value)
    ry = math.degrees(math.asin(float(np.clip(-m[2, 0], -1.0, 1.0))))
    rx = math.degrees(math.atan2(m[2, 1], m[2, 2]))
    rz = math.degrees(math.atan2(m[1, 0], m[0, 0]))
    return np.array([rx, ry, rz])
