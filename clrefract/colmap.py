"""COLMAP sparse models (colmap.github.io/format.html): read as clrefract cameras by `dataset
import`, written from a dataset by `dataset export-colmap`. pycolmap is imported only here and
only when needed (`pip install 'clrefract[colmap]'`).

COLMAP's poses are world-to-camera with OpenCV camera axes (x right, y down, looking down +z);
clrefract's are camera-to-world with OpenGL axes (y up, looking down -z). Both put the top-left
corner of the image at pixel (0, 0) (the first pixel's centre at 0.5), so principal points
carry over as they are.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .cameras import IMAGE_SUFFIXES, Camera, lens_folds
from .dataset import DEFAULT_MARGIN, Dataset, box_from_cameras, default_margin, holdout_split
from .errors import ClrefractError
from .fields.base import Box
from .imageio import HDR_SUFFIXES, ensure_out_dir

INSTALL_HINT = "pip install 'clrefract[colmap]' (or pip install pycolmap)"
MODEL_FOLDERS = ("sparse/0", "sparse", ".")  # where a project keeps its model, in this order
EXTS = (".bin", ".txt")
IMAGE_FOLDER = "images"
# COLMAP's camera models that clrefract reads: clrefract's model, and clrefract's name for each
# of COLMAP's parameters in COLMAP's order (pycolmap's params_info)
READ_MODELS = {
    "SIMPLE_PINHOLE": ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    "PINHOLE": ("PINHOLE", ("fx", "fy", "cx", "cy")),
    "SIMPLE_RADIAL": ("OPENCV", ("f", "cx", "cy", "k1")),
    "RADIAL": ("OPENCV", ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    "FULL_OPENCV": (
        "FULL_OPENCV",
        ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    ),
    "OPENCV_FISHEYE": ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
}
GL_FROM_CV = np.diag([1.0, -1.0, -1.0])  # flips y and z: its own inverse
MIN_BOX_POINTS = 20  # fewer sparse points than this about the object: the cameras' region
BOX_PERCENTILES = (2.0, 98.0)  # of the points on each axis: a few strays do not widen the box
EXPORT_POINTS = 2000  # points spread over a ground-truth surface by export_colmap
# a spread of vectors is flat (near a plane) where its smallest singular value is below
# FLAT_RATIO of the middle one, and that plane is well spanned where the middle one is above
# SPAN_RATIO of the largest (cameras along a line, or all facing one way, fix no normal)
FLAT_RATIO = 0.3
SPAN_RATIO = 0.2
MIN_UP_AGREEMENT = 0.25  # the mean image-up vector's length below which cameras disagree
# a plane normal further than this from the mean image-up vector is a wall of cameras (a
# forward-facing capture), not the ground
MAX_NORMAL_LEAN_DEG = 45.0


def pycolmap_module(where: Path | str):
    try:
        import pycolmap
    except ImportError:
        raise ClrefractError(
            f"{where}: COLMAP models are read and written through pycolmap, which is not "
            f"installed: {INSTALL_HINT}"
        ) from None
    return pycolmap


def find_model(src: Path) -> Path | None:
    """The folder of a COLMAP project's sparse model: src/sparse/0, src/sparse or src itself,
    the first holding cameras and images (.bin or .txt); None without one."""
    for d in (src / sub for sub in MODEL_FOLDERS):
        if any((d / f"cameras{e}").is_file() and (d / f"images{e}").is_file() for e in EXTS):
            return d
    return None


def model_file(model: Path, stem: str) -> Path:
    """A model's cameras, images or points3D file as it is on disk (binary, else text)."""
    binary = model / f"{stem}.bin"
    return binary if binary.is_file() else model / f"{stem}.txt"


def c2w_from_colmap(cam_from_world: np.ndarray) -> np.ndarray:
    """clrefract's camera-to-world 4x4 (OpenGL axes) of COLMAP's 3x4 world-to-camera (OpenCV
    axes)."""
    r, t = cam_from_world[:, :3], cam_from_world[:, 3]
    c2w = np.eye(4)
    c2w[:3, :3] = r.T @ GL_FROM_CV
    c2w[:3, 3] = -r.T @ t
    return c2w


def colmap_from_c2w(c2w: np.ndarray) -> np.ndarray:
    """COLMAP's 3x4 world-to-camera of clrefract's camera-to-world (the inverse of
    c2w_from_colmap)."""
    r = (c2w[:3, :3] @ GL_FROM_CV).T
    return np.hstack([r, (-r @ c2w[:3, 3])[:, None]])


def intrinsics_from_colmap(cam, where: Path) -> dict:
    """Camera keyword arguments (size, focal lengths, principal point, lens) of a pycolmap
    camera; a model clrefract does not read is refused naming `where`."""
    name = cam.model.name
    if name not in READ_MODELS:
        raise ClrefractError(
            f"{where}: camera {cam.camera_id} has model {name}, which clrefract does not read "
            f"(known: {', '.join(READ_MODELS)}); undistort the images first (colmap "
            "image_undistorter)"
        )
    model, names = READ_MODELS[name]
    p = dict(zip(names, (float(v) for v in cam.params)))
    return dict(
        width=int(cam.width),
        height=int(cam.height),
        fl_x=p.get("fx", p.get("f")),
        fl_y=p.get("fy", p.get("f")),
        cx=p["cx"],
        cy=p["cy"],
        camera_model=model,
        distortion={k: v for k, v in p.items() if k[0] in "kp"},
    )


@dataclass
class ColmapCapture:
    """A COLMAP project as cameras: `cameras` are the registered images sorted by name, each
    with file_path 'images/<name>' (its place in the dataset folder written) and the image
    on disk in `sources`; `points` are the sparse points (n, 3) in the model's units."""

    model: Path
    images: Path
    cameras: list[Camera]
    sources: dict[str, Path]
    points: np.ndarray


def read_colmap(src: Path, model: Path, images: Path | None = None) -> ColmapCapture:
    """The cameras, images and sparse points of the COLMAP model in folder `model`, images in
    `images` (default src/images). Refused, naming the file: a model pycolmap cannot read, one
    without registered images, cameras of mixed or unknown models, a missing image."""
    pycolmap = pycolmap_module(model)
    try:
        rec = pycolmap.Reconstruction(str(model))
    except (ValueError, RuntimeError) as exc:
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ClrefractError(f"{model}: not a readable COLMAP model ({msg})") from None
    images_file, cameras_file = model_file(model, "images"), model_file(model, "cameras")
    ids = sorted(rec.reg_image_ids(), key=lambda i: rec.images[i].name)
    if not ids:
        raise ClrefractError(f"{images_file}: the COLMAP model holds no registered images")
    used = sorted({rec.images[i].camera_id for i in ids})
    kinds = sorted({rec.cameras[c].model.name for c in used})
    if len(kinds) > 1:
        raise ClrefractError(
            f"{cameras_file}: cameras of mixed models ({', '.join(kinds)}); clrefract takes "
            "one model per capture: undistort the images first (colmap image_undistorter)"
        )
    intr = {c: intrinsics_from_colmap(rec.cameras[c], cameras_file) for c in used}
    for c, kw in intr.items():
        check_lens(Camera(**kw, c2w=np.eye(4)), f"{cameras_file}: camera {c}")
    folder = Path(images) if images is not None else src / IMAGE_FOLDER
    cams, sources = [], {}
    for i in ids:
        image = rec.images[i]
        if Path(image.name).is_absolute() or ".." in Path(image.name).parts:
            raise ClrefractError(f"{images_file}: image name {image.name!r} leaves the folder")
        path = folder / image.name
        if path.suffix.lower() not in IMAGE_SUFFIXES:
            raise ClrefractError(
                f"{path}: image type {path.suffix or '(none)'} is not read (EXR, PNG or JPEG)"
            )
        if not path.is_file():
            raise ClrefractError(
                f"{path}: image named in {images_file} not found (give the image folder with "
                "--images)"
            )
        pose = image.cam_from_world
        pose = pose() if callable(pose) else pose  # a method since pycolmap 3.12 (rigs)
        rel = f"{IMAGE_FOLDER}/{Path(image.name).as_posix()}"
        c2w = c2w_from_colmap(np.asarray(pose.matrix(), np.float64))
        cams.append(Camera(**intr[image.camera_id], c2w=c2w, name=image.name, file_path=rel))
        sources[rel] = path
    points = np.array([p.xyz for p in rec.points3D.values()], np.float64).reshape(-1, 3)
    return ColmapCapture(model, folder, cams, sources, points)


def check_lens(cam: Camera, where: str) -> None:
    """Refuse a lens that folds the image, as load_transforms refuses one in a transforms
    file."""
    reason = lens_folds(cam)
    if reason is not None:
        raise ClrefractError(
            f"{where}: lens distortion of camera_model {cam.camera_model} folds the image "
            f"({reason})"
        )


def split_by_name(cams: list[Camera], every: int) -> tuple[list[Camera], list[Camera], str]:
    """(train, test, the rule): by the names' first folder where every image lies under
    train/ or test/ and both occur (a model export_colmap wrote), else every `every`-th image
    in name order is a test view."""
    tops = [Path(c.name).parts[0] if len(Path(c.name).parts) > 1 else "" for c in cams]
    if set(tops) == {"train", "test"}:
        train = [c for c, t in zip(cams, tops) if t == "train"]
        return train, [c for c, t in zip(cams, tops) if t == "test"], "train/ and test/ names"
    return *holdout_split(cams, every), f"every {every}th image by name"


def box_from_points(points: np.ndarray, cams: list[Camera], where: str) -> tuple[Box, str]:
    """The object's box (mm) from a sparse model's points (mm), and where it came from.

    The object stands where the cameras look, so only the points inside that region (the box
    of box_from_cameras) count; the box spans their 2nd to 98th percentile on each axis, so a
    few stray points do not widen it, and is widened on each side by a fifth of its largest
    side plus two margins (a fitted field is 1 within a margin of the walls). With fewer than
    MIN_BOX_POINTS points in the region, the region itself."""
    region = box_from_cameras(cams, where)
    lo, hi = np.asarray(region.lo), np.asarray(region.hi)
    inside = points[np.all((points > lo) & (points < hi), axis=1)]
    if len(inside) < MIN_BOX_POINTS:
        return region, (
            f"the cameras ({len(inside)} sparse points in the region they look at, fewer "
            f"than {MIN_BOX_POINTS})"
        )
    p_lo, p_hi = np.percentile(inside, BOX_PERCENTILES, axis=0)
    pad = 0.2 * float(np.max(p_hi - p_lo)) + 2 * DEFAULT_MARGIN
    lo, hi = p_lo - pad, p_hi + pad
    return Box(tuple(lo), tuple(hi), default_margin(lo, hi)), (
        f"the sparse points ({len(inside)} of {len(points)} in the region the cameras look at)"
    )


@dataclass
class Levelling:
    """The turn applied to a COLMAP model's world on import: `rotation` takes the model's
    world to the dataset's (+z up); `up` is the up direction in the model's world and `source`
    says where it came from."""

    rotation: np.ndarray
    up: np.ndarray
    source: str

    @property
    def degrees(self) -> float:
        return float(np.degrees(np.arccos(np.clip(self.up[2], -1.0, 1.0))))


UP_WORDS = ("auto", "keep")  # --up's words: estimate the up direction, or keep the model's


def parse_up(value: str | None) -> str | np.ndarray:
    """'auto' (also for None), 'keep', or the unit vector of 'X,Y,Z' (--up); anything else is
    refused in one line."""
    text = "auto" if value is None else str(value).strip().lower()
    if text in UP_WORDS:
        return text
    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.isfinite(v).all() or not np.linalg.norm(v) > 0:
        raise ClrefractError(
            f"--up: expected auto, keep or X,Y,Z (a nonzero direction in the COLMAP model's "
            f"world), got {value!r}"
        )
    return v / np.linalg.norm(v)


def _flat_normal(vectors: np.ndarray, sign: np.ndarray) -> np.ndarray | None:
    """The normal of the well-spanned plane the rows lie near, on the side of the unit vector
    `sign` and within MAX_NORMAL_LEAN_DEG of it; None where there is no such plane."""
    if len(vectors) < 3:
        return None
    _, s, vt = np.linalg.svd(vectors, full_matrices=False)
    if not (s[1] > SPAN_RATIO * s[0] and s[2] < FLAT_RATIO * s[1]):
        return None
    normal = vt[2] if vt[2] @ sign >= 0 else -vt[2]
    return normal if normal @ sign >= np.cos(np.radians(MAX_NORMAL_LEAN_DEG)) else None


def estimate_up(cams: list[Camera], where: str) -> tuple[np.ndarray, str]:
    """The world's up direction (unit) from the cameras, and which estimate gave it.

    Where the camera centres lie near a plane (an orbit, a turntable) its normal; else, where
    the cameras' image-right axes span a plane (cameras held without roll, facing many ways),
    the normal to them, which unlike the mean image-up vector does not lean towards where the
    cameras pitch; else the mean image-up vector. Both normals are signed to agree with the
    mean image-up vector, and taken only within MAX_NORMAL_LEAN_DEG of it (the plane of a
    forward-facing capture stands upright); cameras that disagree on it are refused."""
    mean = np.mean([c.c2w[:3, 1] for c in cams], axis=0)  # OpenGL: +y is image up
    agree = float(np.linalg.norm(mean))
    if agree < MIN_UP_AGREEMENT:
        raise ClrefractError(
            f"{where}: the cameras disagree on which way is up (mean image-up vector of "
            f"length {agree:.2f}); give the up direction with --up X,Y,Z, or --up keep"
        )
    mean /= agree
    centres = np.array([c.position for c in cams])
    normal = _flat_normal(centres - centres.mean(axis=0), mean)
    if normal is not None:
        return normal, "the plane of the camera centres"
    normal = _flat_normal(np.array([c.c2w[:3, 0] for c in cams]), mean)
    if normal is not None:
        return normal, "the normal to the cameras' image-right axes"
    return mean, "the cameras' mean image-up vector"


def turn_to_z(up: np.ndarray) -> np.ndarray:
    """The least rotation taking the unit vector `up` to +z (a turn about their common
    normal), so that headings stay as they were."""
    axis = np.cross(up, [0.0, 0.0, 1.0])
    sin, cos = float(np.linalg.norm(axis)), float(up[2])
    if sin < 1e-12:  # along z already, or opposite: a half turn about x
        return np.eye(3) if cos > 0 else np.diag([1.0, -1.0, -1.0])
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(axis / sin * np.arctan2(sin, cos)).as_matrix()


def level_capture(capture: ColmapCapture, up: str | np.ndarray) -> tuple[ColmapCapture, Levelling]:
    """The capture with its world turned so that up is +z (cameras and sparse points), and
    the turn. `up` is parse_up's: 'auto' estimates it (estimate_up), 'keep' turns nothing, a
    vector is up in the model's world."""
    where = str(model_file(capture.model, "images"))
    if isinstance(up, str) and up == "keep":
        return capture, Levelling(np.eye(3), np.array([0.0, 0.0, 1.0]), "--up keep")
    if isinstance(up, str):
        vec, source = estimate_up(capture.cameras, where)
    else:
        vec, source = np.asarray(up, np.float64), "--up"
    rot = turn_to_z(vec)
    cams = []
    for cam in capture.cameras:
        c2w = cam.c2w.copy()
        c2w[:3, :] = rot @ c2w[:3, :]
        cams.append(replace(cam, c2w=c2w))
    turned = replace(capture, cameras=cams, points=capture.points @ rot.T)
    return turned, Levelling(rot, vec, source)


def _similarity(similarity) -> tuple[float, np.ndarray, np.ndarray]:
    if similarity is None:
        return 1.0, np.eye(3), np.zeros(3)
    s, r, t = similarity
    r, t = np.asarray(r, np.float64), np.asarray(t, np.float64).reshape(3)
    if not (s > 0 and np.allclose(r.T @ r, np.eye(3), atol=1e-9) and np.linalg.det(r) > 0):
        raise ValueError("export_colmap: similarity needs a positive scale and a rotation")
    return float(s), r, t


def _colmap_camera(pycolmap, cam: Camera, camera_id: int):
    """A pycolmap camera of a clrefract one: PINHOLE, or OpenCV's models (OPENCV with k3
    becomes FULL_OPENCV, which COLMAP's OPENCV lacks)."""
    d = cam.distortion
    if cam.camera_model in ("PINHOLE", "SIMPLE_PINHOLE"):
        model, names = "PINHOLE", READ_MODELS["PINHOLE"][1]
    elif cam.camera_model == "OPENCV" and not d.get("k3"):
        model, names = "OPENCV", READ_MODELS["OPENCV"][1]
    elif cam.camera_model in ("OPENCV", "FULL_OPENCV"):
        model, names = "FULL_OPENCV", READ_MODELS["FULL_OPENCV"][1]
    else:
        model, names = cam.camera_model, READ_MODELS[cam.camera_model][1]
    values = {"fx": cam.fl_x, "fy": cam.fl_y, "cx": cam.cx, "cy": cam.cy}
    params = [values.get(n, d.get(n, 0.0)) for n in names]
    return pycolmap.Camera(
        model=model, width=cam.width, height=cam.height, params=params, camera_id=camera_id
    )


def add_camera(rec, camera) -> None:
    """Add a pycolmap camera to a reconstruction (from pycolmap 3.12 on, with its own rig)."""
    getattr(rec, "add_camera_with_trivial_rig", rec.add_camera)(camera)


def add_posed_image(rec, image, pose) -> None:
    """Add a pycolmap image, registered at `pose` (a pycolmap Rigid3d, world to camera)."""
    if hasattr(rec, "add_image_with_trivial_frame"):  # pycolmap 3.12 on: an image in a rig
        rec.add_image_with_trivial_frame(image, pose)
    else:
        image.cam_from_world = pose
        rec.add_image(image)
        rec.register_image(image.image_id)


def export_colmap(dataset: Path, out: Path, text: bool = False, similarity=None) -> dict:
    """Write a dataset folder as a COLMAP project: out/sparse/0 (binary, or text), its frames
    as they are under out/images/train/ and out/images/test/ (so an import keeps the split),
    and its environment map; the sparse points are spread over the ground-truth surface where
    the dataset has one. `similarity` (s, R, t) takes the dataset's world (mm) to the
    model's: x -> s R x + t. Frames' exposure_scale and masks are not carried (COLMAP has no
    place for them). Returns what was written."""
    pycolmap = pycolmap_module(dataset)
    from .mesh import read_mesh
    from .metrics import sample_surface

    ds = Dataset(Path(dataset))
    s, rot, shift = _similarity(similarity)
    out = Path(out)
    model = out / "sparse" / "0"
    if (out / IMAGE_FOLDER).exists() or model.exists():
        raise ClrefractError(f"{out}: already holds a COLMAP project; choose another --out")
    frames = [(split, cam) for split in ("train", "test") for cam in getattr(ds, split)]
    for _, cam in frames:  # every frame before anything is written
        if not ds.frame_path(cam).is_file():
            raise ClrefractError(f"{ds.frame_path(cam)}: frame not found")
    gt = ds.scene.ground_truth.get("surface")
    points = np.zeros((0, 3))
    if gt and (ds.root / gt).is_file():
        points = sample_surface(*read_mesh(ds.root / gt), EXPORT_POINTS, seed=0)
    ensure_out_dir(out, "COLMAP project folder")
    rec = pycolmap.Reconstruction()
    camera_ids: dict[tuple, int] = {}
    for image_id, (split, cam) in enumerate(frames, start=1):
        key = (cam.width, cam.height, cam.fl_x, cam.fl_y, cam.cx, cam.cy, cam.camera_model)
        key += tuple(sorted(cam.distortion.items()))
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            add_camera(rec, _colmap_camera(pycolmap, cam, camera_ids[key]))
        src = ds.frame_path(cam)
        name = f"{split}/{src.name}"
        c2w = cam.c2w.copy()
        c2w[:3, :3] = rot @ c2w[:3, :3]
        c2w[:3, 3] = s * rot @ c2w[:3, 3] + shift
        image = pycolmap.Image(name=name, camera_id=camera_ids[key], image_id=image_id)
        add_posed_image(rec, image, pycolmap.Rigid3d(colmap_from_c2w(c2w)))
        (out / IMAGE_FOLDER / split).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, out / IMAGE_FOLDER / name)
    for p in points:
        rec.add_point3D(s * rot @ p + shift, pycolmap.Track())
    model.mkdir(parents=True)
    (rec.write_text if text else rec.write_binary)(str(model))
    env = ds.root / ds.scene.envmap
    env_name = "envmap.hdr" if env.suffix.lower() in HDR_SUFFIXES else "envmap.exr"
    shutil.copyfile(env, out / env_name)
    info = {
        "model": str(model),
        "format": "text" if text else "binary",
        "images": len(frames),
        "cameras": len(camera_ids),
        "points": len(points),
        "envmap": env_name,
    }
    env_rot = ds.scene.envmap_matrix()
    env_rot = rot if env_rot is None else rot @ env_rot
    if not np.allclose(env_rot, np.eye(3), atol=1e-12):  # what import's --env-rotation takes
        info["env_rotation"] = euler_degrees(env_rot)
    return info


def euler_degrees(r: np.ndarray) -> list[float]:
    """[rx, ry, rz] degrees of a rotation R = Rz Ry Rx (scene.json's envmap_rotation)."""
    from scipy.spatial.transform import Rotation

    return [float(a) for a in Rotation.from_matrix(r).as_euler("xyz", degrees=True)]
