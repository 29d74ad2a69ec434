"""Cameras in the NeRF / instant-ngp convention (SPEC sections 5 and 6): pinhole, or with the
lens distortion of nerfstudio's camera models (OPENCV, FULL_OPENCV, OPENCV_FISHEYE)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ClrefractError
from .imageio import PathLike, atomic_path, image_size

# Lens models as nerfstudio / instant-ngp transforms.json name them, with the coefficients
# each takes. OPENCV and FULL_OPENCV are OpenCV's (rational) model, OPENCV_FISHEYE its
# equidistant fisheye model (cv2.fisheye).
CAMERA_MODELS = {
    "PINHOLE": (),
    "SIMPLE_PINHOLE": (),
    "OPENCV": ("k1", "k2", "k3", "p1", "p2"),
    "FULL_OPENCV": ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2"),
    "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4"),
}
_NEWTON_ITERATIONS = 30
_NEWTON_TOL_PX = 1e-7  # residual of the undistortion, in pixels


@dataclass
class Camera:
    """Pinhole camera; c2w is camera-to-world with OpenGL axes (looks down -z, y up).

    `distortion` holds the nonzero lens coefficients of `camera_model` (k1.. p2, OpenCV's
    conventions: normalised image coordinates with y down)."""

    width: int
    height: int
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    c2w: np.ndarray = field(repr=False)
    name: str = ""
    file_path: str = ""
    exposure: float = 1.0  # linear radiance = decoded pixel value * exposure
    white_balance: tuple = (1.0, 1.0, 1.0)  # RGB gains, after the exposure
    mask_path: str = ""  # the user's object mask (white: object), relative to the JSON
    camera_model: str = "PINHOLE"
    distortion: dict = field(default_factory=dict)

    def __post_init__(self):
        self.c2w = np.array(self.c2w, dtype=np.float64)
        if self.c2w.shape != (4, 4):
            raise ValueError(f"Camera: c2w must be 4x4, got {self.c2w.shape}")
        self.width, self.height = int(self.width), int(self.height)
        self.white_balance = tuple(float(v) for v in self.white_balance)
        if len(self.white_balance) != 3 or not all(
            math.isfinite(v) and v > 0 for v in self.white_balance
        ):
            raise ValueError(
                f"Camera: white_balance must be 3 positive numbers, got {self.white_balance}"
            )
        if self.camera_model not in CAMERA_MODELS:
            raise ValueError(f"Camera: unknown camera_model {self.camera_model!r}")
        self.distortion = {k: float(v) for k, v in self.distortion.items() if v != 0.0}
        stray = set(self.distortion) - set(CAMERA_MODELS[self.camera_model])
        if stray:
            raise ValueError(f"Camera: {sorted(stray)} are not coefficients of {self.camera_model}")

    @property
    def camera_angle_x(self) -> float:
        return 2.0 * math.atan(self.width / (2.0 * self.fl_x))

    @property
    def position(self) -> np.ndarray:
        return self.c2w[:3, 3].copy()

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions (H*W, 3) float64, row-major, through pixel centres."""
        j, i = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        if self.distortion:
            xd, yd = (j - self.cx) / self.fl_x, (i - self.cy) / self.fl_y
            d_cam, bad = undistort(self.camera_model, self.distortion, xd.ravel(), yd.ravel())
            if bad.any():
                raise ClrefractError(
                    f"camera {self.name or self.file_path}: lens distortion cannot be undone "
                    f"at {int(bad.sum())} pixels (the coefficients fold the image)"
                )
        else:
            d_cam = np.stack(
                [(j - self.cx) / self.fl_x, -(i - self.cy) / self.fl_y, -np.ones_like(j)], axis=-1
            ).reshape(-1, 3)
        d = d_cam @ self.c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(self.c2w[:3, 3], d.shape).copy()
        return o, d

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted normalised coordinates (OpenCV's: y down) of undistorted ones (x, y):
        pixel = (cx + fl_x * xd, cy + fl_y * yd). Beyond the image's widest undistorted radius
        the map goes on radially from there, so that far points cannot fold back into view."""
        if not self.distortion:
            return x, y
        _, _, r_max = _check_lens(self.camera_model, self.distortion, _border(self))
        r = np.hypot(x, y)
        s = np.where(r > r_max, r_max / np.maximum(r, 1e-300), 1.0)
        xd, yd = distort(self.camera_model, self.distortion, x * s, y * s)
        return xd / s, yd / s


def _coeffs(dist: dict) -> dict:
    return {k: float(dist.get(k, 0.0)) for k in ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")}


def _radial(model: str, c: dict, r2: np.ndarray) -> np.ndarray:
    """Radial factor: distorted radius over undistorted radius (fisheye: r2 = theta^2)."""
    if model == "OPENCV_FISHEYE":
        return 1.0 + r2 * (c["k1"] + r2 * (c["k2"] + r2 * (c["k3"] + r2 * c["k4"])))
    num = 1.0 + r2 * (c["k1"] + r2 * (c["k2"] + r2 * c["k3"]))
    return num / (1.0 + r2 * (c["k4"] + r2 * (c["k5"] + r2 * c["k6"])))


def distort(model: str, dist: dict, x: np.ndarray, y: np.ndarray):
    """OpenCV's distortion of normalised coordinates (x, y) = (X/Z, Y/Z), y down."""
    c = _coeffs(dist)
    r2 = x * x + y * y
    if model == "OPENCV_FISHEYE":
        r = np.sqrt(r2)
        theta = np.arctan(r)
        scale = np.where(
            r > 0, theta * _radial(model, c, theta * theta) / np.maximum(r, 1e-300), 1.0
        )
        return x * scale, y * scale
    radial = _radial(model, c, r2)
    xy = x * y
    xd = x * radial + 2.0 * c["p1"] * xy + c["p2"] * (r2 + 2.0 * x * x)
    yd = y * radial + c["p1"] * (r2 + 2.0 * y * y) + 2.0 * c["p2"] * xy
    return xd, yd


def undistort(model: str, dist: dict, xd: np.ndarray, yd: np.ndarray):
    """Camera-frame ray directions (n, 3), OpenGL axes (y up, looking down -z), of distorted
    normalised coordinates, by Newton's method; and where it did not converge (n,) bool."""
    c = _coeffs(dist)
    xd, yd = np.asarray(xd, np.float64), np.asarray(yd, np.float64)
    if model == "OPENCV_FISHEYE":
        # theta_d = theta (1 + k1 theta^2 + ...) solved for the angle theta off the axis
        rd = np.hypot(xd, yd)
        t = np.minimum(rd, np.pi)
        for _ in range(_NEWTON_ITERATIONS):
            t2 = t * t
            f = t * _radial(model, c, t2) - rd
            df = 1.0 + t2 * (
                3 * c["k1"] + t2 * (5 * c["k2"] + t2 * (7 * c["k3"] + t2 * 9 * c["k4"]))
            )
            t = np.clip(t - f / np.where(df > 0, df, np.inf), 0.0, np.pi)
        bad = ~(np.abs(t * _radial(model, c, t * t) - rd) < _NEWTON_TOL_PX * 1e-3)
        s = np.where(rd > 0, np.sin(t) / np.maximum(rd, 1e-300), 1.0)
        return np.stack([xd * s, -yd * s, -np.cos(t)], axis=-1), bad
    x, y = xd.copy(), yd.copy()
    h = 1e-7
    for _ in range(_NEWTON_ITERATIONS):
        fx, fy = distort(model, dist, x, y)
        ex, ey = fx - xd, fy - yd
        # Jacobian by central differences: the solution's accuracy rests on the residual alone
        ax, ay = distort(model, dist, x + h, y)
        bx, by = distort(model, dist, x - h, y)
        j11, j21 = (ax - bx) / (2 * h), (ay - by) / (2 * h)
        ax, ay = distort(model, dist, x, y + h)
        bx, by = distort(model, dist, x, y - h)
        j12, j22 = (ax - bx) / (2 * h), (ay - by) / (2 * h)
        det = j11 * j22 - j12 * j21
        det = np.where(np.abs(det) > 1e-12, det, np.nan)
        x = x - (j22 * ex - j12 * ey) / det
        y = y - (j11 * ey - j21 * ex) / det
    fx, fy = distort(model, dist, x, y)
    bad = ~(np.hypot(fx - xd, fy - yd) < _NEWTON_TOL_PX * 1e-3)
    return np.stack([x, -y, -np.ones_like(x)], axis=-1), bad


def _border(cam: Camera) -> tuple:
    """Distorted normalised coordinates of the image's border pixel centres, and the key that
    identifies the lens and image."""
    w, h = cam.width, cam.height
    cols = np.arange(w) + 0.5
    rows = np.arange(h) + 0.5
    j = np.concatenate([cols, cols, np.full(h, 0.5), np.full(h, w - 0.5)])
    i = np.concatenate([np.full(w, 0.5), np.full(w, h - 0.5), rows, rows])
    key = (w, h, cam.fl_x, cam.fl_y, cam.cx, cam.cy)
    return key, (j - cam.cx) / cam.fl_x, (i - cam.cy) / cam.fl_y


_LENS_CHECKS: dict = {}


def lens_folds(cam: Camera) -> str | None:
    """Why the camera's lens distortion folds its image (not one to one), or None."""
    if not cam.distortion:
        return None
    ok, reason, _ = _check_lens(cam.camera_model, cam.distortion, _border(cam))
    return None if ok else reason


def _check_lens(model: str, dist: dict, border) -> tuple:
    """(ok, reason, r_max): whether the lens maps the image one to one, checked on its
    border (the undistortion converges there) and radially (the distorted radius grows with
    the undistorted one out to the widest the image reaches); r_max is that widest radius
    (fisheye: tan of its angle, capped)."""
    key = (model, tuple(sorted(dist.items())), border[0])
    if key in _LENS_CHECKS:
        return _LENS_CHECKS[key]
    _, xd, yd = border
    d, bad = undistort(model, dist, xd, yd)
    c = _coeffs(dist)
    if model == "OPENCV_FISHEYE":
        angle = np.arctan2(np.hypot(d[:, 0], d[:, 1]), -d[:, 2])
        top = float(np.nanmax(angle)) if np.isfinite(angle).any() else np.pi
        t = np.linspace(0.0, top * 1.01, 4097)
        g = t * _radial(model, c, t * t)
        r_max = math.tan(min(top, 1.55))
        ok_radial = True
    else:
        r = np.hypot(d[:, 0], d[:, 1])
        top = float(np.nanmax(r)) if np.isfinite(r).any() else 0.0
        t = np.linspace(0.0, top * 1.01, 4097)
        den = 1.0 + t * t * (c["k4"] + t * t * (c["k5"] + t * t * c["k6"]))
        g = t * _radial(model, c, t * t)
        r_max = top
        ok_radial = bool((den > 0).all())
    ok_radial = ok_radial and bool(np.all(np.diff(g) > 0))
    if bad.any():
        n = int(bad.sum())
        out = (False, f"undistortion does not converge at {n} border pixels", r_max)
    elif not ok_radial:
        out = (False, "the distorted radius is not increasing over the image", r_max)
    else:
        out = (True, "", r_max)
    if len(_LENS_CHECKS) > 256:
        _LENS_CHECKS.clear()
    _LENS_CHECKS[key] = out
    return out


IMAGE_SUFFIXES = (".exr", ".png", ".jpg", ".jpeg")


def frame_stem(cam: Camera, k: int) -> str:
    """File name without image extension for writing a render of a frame: 'r_000' from
    './test/r_000' and from './test/r_000.exr' alike."""
    name = Path(cam.file_path).name if cam.file_path else ""
    if Path(name).suffix.lower() in IMAGE_SUFFIXES:
        name = Path(name).stem
    return name or cam.name or f"view_{k:03d}"


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """4x4 camera-to-world at `eye` looking at `target`, image up as close to `up` as possible."""
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    n = np.linalg.norm(fwd)
    if not n > 0:
        raise ValueError("look_at: eye and target coincide")
    fwd /= n
    up = np.asarray(up, dtype=np.float64)
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-6 * np.linalg.norm(up):
        # Looking along `up`: any up works, take the world axis least parallel to the view.
        right = np.cross(fwd, np.eye(3)[np.argmin(np.abs(fwd))])
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -fwd, eye
    return c2w


def _square_pixel_intrinsics(width: int, height: int, fov_y_deg: float):
    fl = (height / 2.0) / math.tan(math.radians(fov_y_deg) / 2.0)
    return dict(width=width, height=height, fl_x=fl, fl_y=fl, cx=width / 2.0, cy=height / 2.0)


def fibonacci_sphere_cameras(
    n: int, radius: float = 200.0, width: int = 128, height: int = 128, fov_y_deg: float = 30.0
) -> list[Camera]:
    """n cameras spread evenly over a sphere (golden-angle spiral), all looking at the origin."""
    intr = _square_pixel_intrinsics(width, height, fov_y_deg)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    cams = []
    for k in range(n):
        z = 1.0 - (2.0 * k + 1.0) / n
        r = math.sqrt(max(0.0, 1.0 - z * z))
        eye = radius * np.array([r * math.cos(k * golden), r * math.sin(k * golden), z])
        cams.append(Camera(**intr, c2w=look_at(eye), name=f"view_{k:03d}"))
    return cams


def orbit_cameras(
    n: int,
    radius: float = 200.0,
    elevation_deg: float = 20.0,
    width: int = 128,
    height: int = 128,
    fov_y_deg: float = 30.0,
) -> list[Camera]:
    """n cameras evenly spaced on a ring about +z at the given elevation, looking at the origin."""
    intr = _square_pixel_intrinsics(width, height, fov_y_deg)
    el = math.radians(elevation_deg)
    cams = []
    for k in range(n):
        az = 2.0 * math.pi * k / n
        eye = radius * np.array(
            [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
        )
        cams.append(Camera(**intr, c2w=look_at(eye), name=f"orbit_{k:03d}"))
    return cams


# ---- transforms JSON ----

_INTRINSIC_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")
_IMAGE_EXTS = ("", *IMAGE_SUFFIXES)


def _number(path: Path, where: str, key: str, value, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ClrefractError(f"{path}: {where}'{key}' must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise ClrefractError(f"{path}: {where}'{key}' must be positive, got {value!r}")
    return float(value)


def _size(path: Path, where: str, key: str, value) -> int:
    v = _number(path, where, key, value, positive=True)
    if v != int(v):
        raise ClrefractError(
            f"{path}: {where}'{key}' must be a whole number of pixels, got {value}"
        )
    return int(v)


def _matrix(path: Path, where: str, value) -> np.ndarray:
    try:
        m = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape != (4, 4):
        shape = "" if m is None else f" (shape {m.shape})"
        raise ClrefractError(f"{path}: {where}'transform_matrix' must be a 4x4 matrix{shape}")
    if not np.isfinite(m).all():
        raise ClrefractError(f"{path}: {where}'transform_matrix' has non-finite entries")
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
        raise ClrefractError(f"{path}: {where}'transform_matrix' last row must be [0, 0, 0, 1]")
    r = m[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-3) or np.linalg.det(r) < 0:
        raise ClrefractError(
            f"{path}: {where}'transform_matrix' rotation part is not a rotation "
            "(scaled, sheared or mirrored)"
        )
    return m


def _find_image(base: Path, file_path: str) -> Path | None:
    # NeRF synthetic data often omits the extension ("./train/r_0" means r_0.png).
    for ext in _IMAGE_EXTS:
        p = base / (file_path + ext)
        if p.is_file():
            return p
    return None


def _focal(path: Path, where: str, p: dict, axis: str, size: int) -> float | None:
    """Focal length in pixels along `axis` from fl_<axis> or camera_angle_<axis>, or None."""
    if f"fl_{axis}" in p:
        return _number(path, where, f"fl_{axis}", p[f"fl_{axis}"], positive=True)
    key = f"camera_angle_{axis}"
    if key not in p:
        return None
    angle = _number(path, where, key, p[key], positive=True)
    if angle >= math.pi:
        raise ClrefractError(f"{path}: {where}'{key}' must be below pi radians")
    return size / (2.0 * math.tan(angle / 2.0))


def _frame_camera(path: Path, top: dict, frame, k: int) -> Camera:
    where = f"frames[{k}]: "
    if not isinstance(frame, dict):
        raise ClrefractError(f"{path}: {where}must be an object, got {type(frame).__name__}")
    if "transform_matrix" not in frame:
        raise ClrefractError(f"{path}: {where}missing 'transform_matrix'")
    c2w = _matrix(path, where, frame["transform_matrix"])
    file_path = frame.get("file_path", "")
    if not isinstance(file_path, str):
        raise ClrefractError(f"{path}: {where}'file_path' must be a string")
    # Per-frame intrinsics override the top-level ones.
    # A frame that names its own camera_model has its own lens: no coefficient of the top's.
    lens = () if "camera_model" in frame else _DISTORTION_KEYS
    p = {key: top[key] for key in _INTRINSIC_KEYS + lens if key in top}
    p.update({key: frame[key] for key in _INTRINSIC_KEYS + _DISTORTION_KEYS if key in frame})
    for key in _INTRINSIC_KEYS:  # even those another key overrides: garbage is a mistake
        if key in p:
            _number(path, where, key, p[key])
    dist = {key: _number(path, where, key, p[key]) for key in _DISTORTION_KEYS if key in p}
    dist = {key: v for key, v in dist.items() if v != 0.0}
    model = frame.get("camera_model", top.get("camera_model"))
    if model is None:  # instant-ngp writes coefficients without a model: OpenCV's
        model = "OPENCV" if dist else "PINHOLE"
    if not isinstance(model, str) or model.upper() not in CAMERA_MODELS:
        raise ClrefractError(
            f"{path}: {where}unknown camera_model {model!r} (known: {', '.join(CAMERA_MODELS)})"
        )
    model = model.upper()
    stray = sorted(set(dist) - set(CAMERA_MODELS[model]))
    if stray:
        raise ClrefractError(
            f"{path}: {where}lens distortion {', '.join(map(repr, stray))} is not a "
            f"coefficient of camera_model {model}"
        )

    if "w" in p and "h" in p:
        w, h = _size(path, where, "w", p["w"]), _size(path, where, "h", p["h"])
    else:
        image = _find_image(path.parent, file_path) if file_path else None
        if image is None:
            raise ClrefractError(
                f"{path}: {where}image size unknown: give 'w' and 'h', or put the image "
                f"'{file_path}' beside the JSON"
            )
        w, h = image_size(image)
        w = _size(path, where, "w", p["w"]) if "w" in p else w
        h = _size(path, where, "h", p["h"]) if "h" in p else h

    fl_x = _focal(path, where, p, "x", w)
    if fl_x is None:
        raise ClrefractError(f"{path}: {where}missing intrinsics: need 'camera_angle_x' or 'fl_x'")
    fl_y = _focal(path, where, p, "y", h)
    fl_y = fl_x if fl_y is None else fl_y  # square pixels
    cx = _number(path, where, "cx", p["cx"]) if "cx" in p else w / 2.0
    cy = _number(path, where, "cy", p["cy"]) if "cy" in p else h / 2.0
    name = Path(file_path).name if file_path else f"frame_{k:03d}"
    exposure = frame.get("exposure_scale", top.get("exposure_scale", 1.0))
    exposure = _number(path, where, "exposure_scale", exposure, positive=True)
    white_balance = frame.get("white_balance", top.get("white_balance", [1.0, 1.0, 1.0]))
    if not (
        isinstance(white_balance, list)
        and len(white_balance) == 3
        and all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0
            for v in white_balance
        )
    ):
        raise ClrefractError(
            f"{path}: {where}'white_balance' must be 3 positive numbers (R, G, B gains), "
            f"got {white_balance!r}"
        )
    mask_path = frame.get("mask_path", "")
    if not isinstance(mask_path, str):
        raise ClrefractError(f"{path}: {where}'mask_path' must be a string")
    cam = Camera(
        w,
        h,
        fl_x,
        fl_y,
        cx,
        cy,
        c2w,
        name=name,
        file_path=file_path,
        exposure=exposure,
        white_balance=tuple(white_balance),
        mask_path=mask_path,
        camera_model=model,
        distortion=dist,
    )
    reason = lens_folds(cam)
    if reason is not None:
        raise ClrefractError(
            f"{path}: {where}lens distortion of camera_model {model} folds the image ({reason})"
        )
    return cam


def load_transforms(path: PathLike) -> list[Camera]:
    """Cameras from a NeRF / instant-ngp transforms JSON; malformed input -> ClrefractError."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ClrefractError(f"{path}: transforms file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ClrefractError(f"{path}: cannot read transforms file ({e})") from None
    try:
        top = json.loads(text)
    except json.JSONDecodeError as e:
        raise ClrefractError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(top, dict):
        raise ClrefractError(f"{path}: top level must be a JSON object")
    frames = top.get("frames")
    if not isinstance(frames, list):
        raise ClrefractError(f"{path}: missing 'frames' list")
    if not frames:
        raise ClrefractError(f"{path}: 'frames' is empty")
    cams = [_frame_camera(path, top, fr, k) for k, fr in enumerate(frames)]
    _refuse_duplicates(path, cams)
    return cams


def _refuse_duplicates(path: Path, cams: list[Camera]) -> None:
    """Two frames of one image would be weighted twice, and their renders overwrite each
    other."""
    seen: dict[str, int] = {}
    for k, cam in enumerate(cams):
        if not cam.file_path:
            continue
        key = str(Path(cam.file_path))
        if Path(key).suffix.lower() in IMAGE_SUFFIXES:
            key = str(Path(key).with_suffix(""))
        if key in seen:
            raise ClrefractError(
                f"{path}: frames[{k}] repeats the image of frames[{seen[key]}] ({cam.file_path!r})"
            )
        seen[key] = k


def _intrinsics(cam: Camera) -> dict:
    out = {
        "camera_angle_x": cam.camera_angle_x,
        "w": cam.width,
        "h": cam.height,
        "fl_x": cam.fl_x,
        "fl_y": cam.fl_y,
        "cx": cam.cx,
        "cy": cam.cy,
    }
    if cam.distortion or cam.camera_model not in ("PINHOLE", "SIMPLE_PINHOLE"):
        out["camera_model"] = cam.camera_model
        out.update({k: cam.distortion.get(k, 0.0) for k in CAMERA_MODELS[cam.camera_model]})
    return out


def save_transforms(path: PathLike, cameras: list[Camera], extra: dict | None = None) -> None:
    """Write cameras as a transforms JSON (atomically); `extra` adds top-level keys."""
    if not cameras:
        raise ValueError("save_transforms: no cameras")
    top = _intrinsics(cameras[0])
    if extra:
        clash = set(extra) & (set(top) | {"frames"})
        if clash:
            raise ValueError(f"save_transforms: extra keys {sorted(clash)} are reserved")
        top.update(extra)
    frames = []
    for k, cam in enumerate(cameras):
        fr = {
            "file_path": cam.file_path or cam.name or f"frame_{k:03d}",
            "transform_matrix": cam.c2w.tolist(),
        }
        if cam.exposure != 1.0:
            fr["exposure_scale"] = cam.exposure
        if cam.white_balance != (1.0, 1.0, 1.0):
            fr["white_balance"] = list(cam.white_balance)
        if cam.mask_path:
            fr["mask_path"] = cam.mask_path
        intr = _intrinsics(cam)
        # Only cameras that differ from the first carry their own intrinsics, with every
        # lens key the first has (a pinhole among distorted cameras: its model and zeros).
        lens = ("camera_model", *_DISTORTION_KEYS)
        if any(intr.get(key) != top.get(key) for key in set(intr) | set(lens)):
            intr.setdefault("camera_model", cam.camera_model)
            intr.update({k: 0.0 for k in _DISTORTION_KEYS if k in top and k not in intr})
            fr.update(intr)
        frames.append(fr)
    top["frames"] = frames
    with atomic_path(path, suffix=".json") as tmp:
        tmp.write_text(json.dumps(top, indent=2) + "\n", encoding="utf-8")
