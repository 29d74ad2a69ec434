"""Datasets on disk (SPEC section 6): NeRF-convention transforms, linear EXR views, the
environment map and a scene file; read, written and checked here.

    DIR/scene.json              box, units, eta range, object, file names
    DIR/transforms_train.json   cameras (camera-to-world, OpenGL axes) and frame paths
    DIR/transforms_test.json
    DIR/train/r_000.exr (+ .png preview), DIR/test/r_000.exr, ...
    DIR/envmap.exr
    DIR/gt_eta.npz, DIR/gt_surface.ply   (synthetic scenes only)
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .cameras import IMAGE_SUFFIXES, Camera, load_transforms
from .envmap import EnvMap
from .errors import ClrefractError
from .fields.base import Box
from .imageio import atomic_path, read_frame
from .limits import check_training_rays

SCENE_FILE = "scene.json"
FORMAT = "clrefract-dataset"


@dataclass
class Scene:
    box: Box
    eta_range: tuple[float, float]
    object: dict | None = None  # the analytic object of a synthetic scene
    envmap: str = "envmap.exr"
    train: str = "transforms_train.json"
    test: str = "transforms_test.json"
    ground_truth: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": 1,
            "units": "mm",
            "box": self.box.to_dict(),
            "eta_range": list(self.eta_range),
            "object": self.object,
            "envmap": self.envmap,
            "train": self.train,
            "test": self.test,
            "ground_truth": self.ground_truth,
            **self.extra,
        }


def write_scene(root: Path, scene: Scene) -> None:
    with atomic_path(root / SCENE_FILE, suffix=".json") as tmp:
        tmp.write_text(json.dumps(scene.to_dict(), indent=2) + "\n")


def _numbers(value, n: int) -> bool:
    """Whether value is a list of n finite numbers (JSON true/false are not numbers)."""
    return (
        isinstance(value, list | tuple)
        and len(value) == n
        and all(
            isinstance(x, int | float) and not isinstance(x, bool) and np.isfinite(x) for x in value
        )
    )


def read_scene(root: Path) -> Scene:
    path = Path(root) / SCENE_FILE
    if not path.is_file():
        raise ClrefractError(f"{path}: scene file not found (is {root} a clrefract dataset?)")
    try:
        d = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ClrefractError(f"{path}: cannot read scene file ({exc})") from None
    if not isinstance(d, dict):
        raise ClrefractError(f"{path}: top level must be a JSON object")
    try:
        box = Box.from_dict(d["box"]) if "box" in d else Box()
        eta = d.get("eta_range", (1.0, 1.6))
        if not _numbers(eta, 2) or not 1.0 <= eta[0] < eta[1]:
            raise ValueError(f"eta_range must be [lo, hi] with 1 <= lo < hi, got {eta!r}")
        eta = (float(eta[0]), float(eta[1]))
    except (KeyError, TypeError, ValueError, ClrefractError) as exc:
        raise ClrefractError(f"{path}: bad scene description ({exc})") from None
    known = {
        "format",
        "version",
        "units",
        "box",
        "eta_range",
        "object",
        "envmap",
        "train",
        "test",
        "ground_truth",
    }
    return Scene(
        box=box,
        eta_range=eta,
        object=d.get("object"),
        envmap=d.get("envmap", "envmap.exr"),
        train=d.get("train", "transforms_train.json"),
        test=d.get("test", "transforms_test.json"),
        ground_truth=d.get("ground_truth", {}) or {},
        extra={k: v for k, v in d.items() if k not in known},
    )


def frame_suffix(root: Path, cams: list[Camera]) -> str:
    """The image type of frames named without one ('./train/r_0'): that of the first such
    frame on disk, EXR before PNG and JPEG (clrefract's own datasets keep PNG previews beside
    their EXR frames), and one type for all, so that a missing EXR is reported rather than
    replaced by its preview."""
    for cam in cams:
        p = Path(root) / cam.file_path
        if cam.file_path and p.suffix.lower() not in IMAGE_SUFFIXES:
            for suffix in IMAGE_SUFFIXES:
                if p.with_name(p.name + suffix).is_file():
                    return suffix
            break
    return ".exr"


def frame_image_path(root: Path, cam: Camera, suffix: str = ".exr") -> Path:
    p = Path(root) / cam.file_path
    return p if p.suffix.lower() in IMAGE_SUFFIXES else p.with_name(p.name + suffix)


def read_frame_image(path: Path, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """A frame's linear image (times its exposure) and the loss weight of each pixel (0 where
    the photograph clipped: its radiance is unknown), checked against its camera."""
    img, clipped = read_frame(path)
    if img.shape[:2] != (cam.height, cam.width):
        raise ClrefractError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]} but its "
            f"camera says {cam.width}x{cam.height}"
        )
    if not np.isfinite(img).all():
        raise ClrefractError(f"{path}: image has NaN or infinite pixels")
    weight = np.ones(img.shape[:2], np.float32)
    if clipped is not None:
        weight[clipped] = 0.0
    return img * np.float32(cam.exposure), weight


def sees_box(cam: Camera, box: Box) -> bool:
    """Whether any part of the box can be in the camera's image: the box of the projected
    corners overlaps the image (a box that straddles the camera's plane counts as seen)."""
    corners = np.array(
        [
            [x, y, z]
            for x in (box.lo[0], box.hi[0])
            for y in (box.lo[1], box.hi[1])
            for z in (box.lo[2], box.hi[2])
        ]
    )
    p = (corners - cam.c2w[:3, 3]) @ cam.c2w[:3, :3]  # camera axes: looks down -z
    depth = -p[:, 2]
    if np.all(depth <= 0):
        return False
    if np.any(depth <= 0):
        return True
    u = cam.cx + cam.fl_x * p[:, 0] / depth
    v = cam.cy - cam.fl_y * p[:, 1] / depth
    return bool(u.max() > 0 and u.min() < cam.width and v.max() > 0 and v.min() < cam.height)


class Dataset:
    """A dataset folder: scene, cameras, images (read on demand) and environment map."""

    def __init__(self, root):
        self.root = Path(root)
        if not self.root.is_dir():
            raise ClrefractError(f"{self.root}: dataset folder not found")
        self.scene = read_scene(self.root)
        self.train = load_transforms(self.root / self.scene.train)
        self.test = load_transforms(self.root / self.scene.test)
        self.suffix = frame_suffix(self.root, self.train + self.test)
        self._weights: dict[str, np.ndarray] = {}

    @property
    def box(self) -> Box:
        return self.scene.box

    def envmap(self) -> EnvMap:
        return EnvMap.from_exr(self.root / self.scene.envmap)

    def frame(self, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Linear image (H, W, 3) and per-pixel loss weights (H, W) of a frame."""
        return read_frame_image(frame_image_path(self.root, cam, self.suffix), cam)

    def image(self, cam: Camera) -> np.ndarray:
        return self.frame(cam)[0]

    def pixel_weights(self, split: str = "train") -> np.ndarray:
        """Loss weights (n,) of a split's pixels in the order of rays_and_pixels: 0 where a
        photograph clipped."""
        if split not in self._weights:
            self.rays_and_pixels(split)
        return self._weights[split]

    def rays_and_pixels(self, split: str = "train"):
        """All rays of a split with their target radiance: origins, dirs (n, 3), rgb (n, 3)."""
        cams = self.train if split == "train" else self.test
        source = self.root / (self.scene.train if split == "train" else self.scene.test)
        for k, cam in enumerate(cams):
            if not sees_box(cam, self.box):
                raise ClrefractError(
                    f"{source}: frame {k} ({cam.file_path or cam.name}) does not see the "
                    f"object's box {list(self.box.lo)}..{list(self.box.hi)} mm (wrong poses, "
                    "units or box?)"
                )
        check_training_rays(str(source), sum(c.width * c.height for c in cams))
        os_, ds, px, wt = [], [], [], []
        for cam in cams:
            o, d = cam.rays()
            os_.append(o)
            ds.append(d)
            img, weight = self.frame(cam)
            px.append(img.reshape(-1, 3))
            wt.append(weight.ravel())
        self._weights[split] = np.concatenate(wt).astype(np.float64)
        return np.concatenate(os_), np.concatenate(ds), np.concatenate(px).astype(np.float64)


def check_dataset(root) -> list[str]:
    """Every problem found in a dataset folder, as messages naming the file (empty: fine)."""
    root = Path(root)
    problems: list[str] = []
    if not root.is_dir():
        return [f"{root}: dataset folder not found"]
    try:
        scene = read_scene(root)
    except ClrefractError as exc:
        return [str(exc)]
    try:
        EnvMap.from_exr(root / scene.envmap)
    except ClrefractError as exc:
        problems.append(str(exc))
    lo, hi = np.asarray(scene.box.lo), np.asarray(scene.box.hi)
    centre, half = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    for split in (scene.train, scene.test):
        try:
            cams = load_transforms(root / split)
        except ClrefractError as exc:
            problems.append(str(exc))
            continue
        suffix = frame_suffix(root, cams)
        for k, cam in enumerate(cams):
            where = f"{root / split}: frame {k} ({cam.file_path or 'no file_path'})"
            # the view ray through the image centre must pass near the box
            c = cam.c2w[:3, 3]
            fwd = -cam.c2w[:3, 2] / np.linalg.norm(cam.c2w[:3, 2])
            t = max(float((centre - c) @ fwd), 0.0)
            if np.linalg.norm(c + t * fwd - centre) > half:
                problems.append(f"{where}: camera does not look at the box")
            elif not sees_box(cam, scene.box):
                problems.append(f"{where}: camera does not see the box at all")
            if np.all((c > lo) & (c < hi)):
                problems.append(f"{where}: camera is inside the box")
            path = frame_image_path(root, cam, suffix)
            if not path.is_file():
                problems.append(f"{where}: image {path} is missing")
                continue
            try:
                img = read_frame(path)[0]
            except ClrefractError as exc:
                problems.append(str(exc))
                continue
            if img.shape[:2] != (cam.height, cam.width):
                problems.append(
                    f"{path}: image is {img.shape[1]}x{img.shape[0]} but its "
                    f"camera says {cam.width}x{cam.height}"
                )
            if not np.isfinite(img).all():
                bad = int((~np.isfinite(img)).any(axis=-1).sum())
                problems.append(f"{path}: {bad} pixel(s) with non-finite values")
    return problems
