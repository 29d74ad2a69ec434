"""Pinhole cameras in the NeRF / instant-ngp convention (SPEC sections 5 and 6)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ClrefractError
from .imageio import PathLike, atomic_path, image_size


@dataclass
class Camera:
    """Pinhole camera; c2w is camera-to-world with OpenGL axes (looks down -z, y up)."""

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
    mask_path: str = ""  # the user's object mask (white: object), relative to the JSON

    def __post_init__(self):
        self.c2w = np.array(self.c2w, dtype=np.float64)
        if self.c2w.shape != (4, 4):
            raise ValueError(f"Camera: c2w must be 4x4, got {self.c2w.shape}")
        self.width, self.height = int(self.width), int(self.height)

    @property
    def camera_angle_x(self) -> float:
        return 2.0 * math.atan(self.width / (2.0 * self.fl_x))

    @property
    def position(self) -> np.ndarray:
        return self.c2w[:3, 3].copy()

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions (H*W, 3) float64, row-major, through pixel centres."""
        j, i = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        d_cam = np.stack(
            [(j - self.cx) / self.fl_x, -(i - self.cy) / self.fl_y, -np.ones_like(j)], axis=-1
        ).reshape(-1, 3)
        d = d_cam @ self.c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(self.c2w[:3, 3], d.shape).copy()
        return o, d


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
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
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
    p = {key: top[key] for key in _INTRINSIC_KEYS + _DISTORTION_KEYS if key in top}
    p.update({key: frame[key] for key in _INTRINSIC_KEYS + _DISTORTION_KEYS if key in frame})
    for key in _INTRINSIC_KEYS:  # even those another key overrides: garbage is a mistake
        if key in p:
            _number(path, where, key, p[key])
    for key in _DISTORTION_KEYS:
        if key in p and _number(path, where, key, p[key]) != 0.0:
            raise ClrefractError(f"{path}: {where}lens distortion '{key}' is not supported")

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
    mask_path = frame.get("mask_path", "")
    if not isinstance(mask_path, str):
        raise ClrefractError(f"{path}: {where}'mask_path' must be a string")
    return Camera(
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
        mask_path=mask_path,
    )


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
    return {
        "camera_angle_x": cam.camera_angle_x,
        "w": cam.width,
        "h": cam.height,
        "fl_x": cam.fl_x,
        "fl_y": cam.fl_y,
        "cx": cam.cx,
        "cy": cam.cy,
    }


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
        if cam.mask_path:
            fr["mask_path"] = cam.mask_path
        intr = _intrinsics(cam)
        # Only cameras that differ from the first carry their own intrinsics.
        if any(intr[key] != top[key] for key in intr):
            fr.update(intr)
        frames.append(fr)
    top["frames"] = frames
    with atomic_path(path, suffix=".json") as tmp:
        tmp.write_text(json.dumps(top, indent=2) + "\n", encoding="utf-8")
