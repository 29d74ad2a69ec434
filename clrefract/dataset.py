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

from .cameras import IMAGE_SUFFIXES, Camera, frame_stem, load_transforms
from .envmap import EnvMap, rotation_matrix
from .errors import ClrefractError
from .fields.base import Box
from .imageio import atomic_path, chroma_halved, read_frame_rgba
from .limits import check_training_rays

SCENE_FILE = "scene.json"
FORMAT = "clrefract-dataset"


# scene.json, every key optional (docs/formats.md lists them):
DEFAULT_ETA_RANGE = (1.0, 1.6)  # glass and water lie inside
DEFAULT_MARGIN = 4.0  # mm; at most a tenth of the box's smallest side
DEFAULT_HOLDOUT = 8  # one transforms file: every 8th frame is a test view
TRAIN_FILES = ("transforms_train.json", "transforms.json")
TEST_FILE = "transforms_test.json"


@dataclass
class Scene:
    box: Box | None  # None: the region the cameras all look at (Dataset fills it in)
    eta_range: tuple[float, float]
    object: dict | None = None  # the analytic object of a synthetic scene
    envmap: str = "envmap.exr"
    envmap_rotation: list | None = None  # [rx, ry, rz] degrees or a 3x3 matrix; None: none
    train: str = "transforms_train.json"
    test: str = "transforms_test.json"  # the train file itself: every holdout_every-th frame
    ground_truth: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    frames: str = ""  # image type of frames named without one; "": the type found on disk
    holdout_every: int = DEFAULT_HOLDOUT
    assumed: list[str] = field(default_factory=list)  # keys taken by default, in words

    def to_dict(self) -> dict:
        d = {
            "format": FORMAT,
            "version": 1,
            "units": "mm",
            "box": self.box.to_dict() if self.box is not None else None,
            "eta_range": list(self.eta_range),
            "object": self.object,
            "envmap": self.envmap,
            **({"envmap_rotation": self.envmap_rotation} if self.envmap_rotation else {}),
            "train": self.train,
            "test": self.test,
            "ground_truth": self.ground_truth,
            **self.extra,
        }
        if d["box"] is None:
            del d["box"]
        if self.frames:
            d["frames"] = self.frames
        if self.test == self.train:
            d["holdout_every"] = self.holdout_every
        return d

    def envmap_matrix(self) -> np.ndarray | None:
        """The panorama's rotation into the world (3x3), None without one."""
        return None if self.envmap_rotation is None else rotation_matrix(self.envmap_rotation)


def write_scene(root: Path, scene: Scene) -> None:
    with atomic_path(root / SCENE_FILE, suffix=".json") as tmp:
        tmp.write_text(json.dumps(scene.to_dict(), indent=2) + "\n")


def finite_numbers(value, n: int) -> bool:
    """Whether value is a list of n finite numbers (JSON true/false are not numbers)."""
    return (
        isinstance(value, list | tuple)
        and len(value) == n
        and all(
            isinstance(x, int | float) and not isinstance(x, bool) and np.isfinite(x) for x in value
        )
    )


def default_margin(lo, hi) -> float:
    return float(min(DEFAULT_MARGIN, np.min(np.asarray(hi) - np.asarray(lo)) / 10))


BOX_HELP = "xmin,ymin,zmin,xmax,ymax,zmax"


def box_values(values, what: str = "--box") -> list[float]:
    """The six numbers of a box option, given as one comma-separated string or as separate
    values (or both): xmin, ymin, zmin, xmax, ymax, zmax, each minimum below its maximum."""
    items = [values] if isinstance(values, str) else list(values)
    words = [w for item in items for w in str(item).replace(",", " ").split()]
    if len(words) != 6:
        raise ClrefractError(f"{what} needs six numbers {BOX_HELP}, got {len(words)}")
    try:
        nums = [float(w) for w in words]
    except ValueError:
        bad = next(w for w in words if not _is_float(w))
        raise ClrefractError(f"{what}: {bad!r} is not a number ({BOX_HELP})") from None
    if not all(np.isfinite(nums)):
        raise ClrefractError(f"{what}: every number must be finite, got {words}")
    for a, lo, hi in zip("xyz", nums[:3], nums[3:]):
        if not lo < hi:
            raise ClrefractError(f"{what}: {a}min must be below {a}max, got {lo:g} >= {hi:g}")
    return nums


def _is_float(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def box_of(values, scale: float = 1.0, what: str = "--box") -> Box:
    """A Box (mm) from box option values in units of `scale` mm, with the default margin."""
    nums = np.array(box_values(values, what)) * scale
    return Box(tuple(nums[:3]), tuple(nums[3:]), default_margin(nums[:3], nums[3:]))


def _box(path: Path, d) -> Box:
    if not isinstance(d, dict):
        raise ClrefractError(f"{path}: 'box' must be an object with 'lo', 'hi' and 'margin'")
    for key, words in (("lo", "lowest"), ("hi", "highest")):
        if key not in d:
            raise ClrefractError(
                f"{path}: 'box' needs '{key}', its {words} corner [x, y, z] in mm (or leave "
                "out 'box' to take it from the cameras)"
            )
        if not finite_numbers(d[key], 3):
            raise ClrefractError(f"{path}: box '{key}' must be 3 numbers (mm), got {d[key]!r}")
    margin = d.get("margin", default_margin(d["lo"], d["hi"]))
    if not finite_numbers([margin], 1):
        raise ClrefractError(f"{path}: box 'margin' must be a number of mm, got {margin!r}")
    try:
        return Box(tuple(map(float, d["lo"])), tuple(map(float, d["hi"])), float(margin))
    except ClrefractError as exc:
        raise ClrefractError(f"{path}: {exc}") from None


def _string(path: Path, d: dict, key: str, default: str) -> str:
    v = d.get(key, default)
    if not isinstance(v, str) or not v:
        raise ClrefractError(f"{path}: '{key}' must be a file name, got {v!r}")
    return v


def _load_scene_file(path: Path) -> dict:
    try:
        d = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ClrefractError(f"{path}: cannot read scene file ({exc})") from None
    if not isinstance(d, dict):
        raise ClrefractError(f"{path}: top level must be a JSON object")
    return d


def _transforms_files(root: Path, d: dict, path: Path, assumed: list[str]) -> tuple[str, str]:
    if "train" in d:
        train = _string(path, d, "train", "")
    else:
        train = next((f for f in TRAIN_FILES if (root / f).is_file()), TRAIN_FILES[0])
        assumed.append(f"train: cameras from {train}")
    if "test" in d:
        test = _string(path, d, "test", "")
    elif (root / TEST_FILE).is_file() or train == TRAIN_FILES[0]:
        test = TEST_FILE
        assumed.append(f"test: cameras from {test}")
    else:
        test = train
        assumed.append(f"test: every {DEFAULT_HOLDOUT}th frame of {train} held out")
    return train, test


def read_scene(root: Path) -> Scene:
    """The scene of a dataset folder: scene.json where there is one, defaults for every key
    it lacks (or for all, without one), listed in words in Scene.assumed."""
    root = Path(root)
    path = root / SCENE_FILE
    d = _load_scene_file(path) if path.is_file() else {}
    assumed: list[str] = [] if path.is_file() else [f"no {SCENE_FILE}: every key by default"]
    units = d.get("units", "mm")
    if units != "mm":
        raise ClrefractError(
            f'{path}: units must be "mm", got {units!r} (`clrefract dataset import --scale` '
            "converts a capture to millimetres)"
        )
    box = _box(path, d["box"]) if "box" in d else None
    if box is None:
        assumed.append("box: the region all cameras look at")
    elif "margin" not in d["box"]:
        assumed.append(f"box margin: {box.margin:g} mm")
    eta = d.get("eta_range", DEFAULT_ETA_RANGE)
    if not finite_numbers(eta, 2) or not 1.0 <= eta[0] < eta[1]:
        raise ClrefractError(
            f"{path}: 'eta_range' must be [lo, hi], numbers with 1 <= lo < hi, got {eta!r}"
        )
    if "eta_range" not in d:
        assumed.append(f"eta_range: {list(DEFAULT_ETA_RANGE)}")
    envmap = _string(path, d, "envmap", "envmap.exr")
    if "envmap" not in d:
        assumed.append("envmap: envmap.exr")
    env_rotation = d.get("envmap_rotation")
    if env_rotation is not None:
        try:
            rotation_matrix(env_rotation)
        except ValueError as exc:
            raise ClrefractError(f"{path}: 'envmap_rotation' {exc}") from None
    train, test = _transforms_files(root, d, path, assumed)
    holdout = d.get("holdout_every", DEFAULT_HOLDOUT)
    if isinstance(holdout, bool) or not isinstance(holdout, int) or holdout < 2:
        raise ClrefractError(f"{path}: 'holdout_every' must be a whole number >= 2")
    frames = d.get("frames", ".exr" if d.get("format") == FORMAT else "")
    if frames and frames not in IMAGE_SUFFIXES:
        raise ClrefractError(f"{path}: 'frames' must be one of {', '.join(IMAGE_SUFFIXES)}")
    gt = d.get("ground_truth", {}) or {}
    if not isinstance(gt, dict):
        raise ClrefractError(f"{path}: 'ground_truth' must be an object")
    known = {"format", "version", "units", "box", "eta_range", "object", "envmap", "train"}
    known |= {"envmap_rotation"}
    known |= {"test", "ground_truth", "frames", "holdout_every"}
    return Scene(
        box=box,
        eta_range=(float(eta[0]), float(eta[1])),
        object=d.get("object"),
        envmap=envmap,
        envmap_rotation=env_rotation,
        train=train,
        test=test,
        ground_truth=gt,
        extra={k: v for k, v in d.items() if k not in known},
        frames=frames,
        holdout_every=holdout,
        assumed=assumed,
    )


def box_from_cameras(cams: list[Camera], where: str) -> Box:
    """The region every camera looks at: centred on the point nearest all optical axes, as
    wide as the narrowest view is there (so the whole box is in every image)."""
    eye = np.array([c.c2w[:3, 3] for c in cams])
    fwd = np.array([-c.c2w[:3, 2] / np.linalg.norm(c.c2w[:3, 2]) for c in cams])
    proj = np.eye(3)[None] - fwd[:, :, None] * fwd[:, None, :]  # off-axis part, per camera
    a, b = proj.sum(0), np.einsum("nij,nj->i", proj, eye)
    if len(cams) < 2 or np.linalg.cond(a) > 1e8:
        raise ClrefractError(
            f"{where}: the cameras do not look at one common point (parallel views?); give "
            "the object's box in scene.json"
        )
    centre = np.linalg.solve(a, b)
    depth = np.einsum("ni,ni->n", centre - eye, fwd)
    if np.any(depth <= 0):
        k = int(np.argmin(depth))
        raise ClrefractError(
            f"{where}: frame {k} ({cams[k].file_path or cams[k].name}) looks away from the "
            "point the other cameras look at; give the object's box in scene.json"
        )
    tan_half = np.array([min(c.width / 2 / c.fl_x, c.height / 2 / c.fl_y) for c in cams])
    half = float(np.min(depth * tan_half)) / np.sqrt(3)  # the box's corners stay in view
    lo, hi = centre - half, centre + half
    return Box(tuple(lo), tuple(hi), default_margin(lo, hi))


def load_cameras(root: Path, scene: Scene) -> tuple[list[Camera], list[Camera]]:
    """Training and test cameras of a scene; one transforms file is split by holdout."""
    train = load_transforms(root / scene.train)
    if scene.test != scene.train:
        return train, load_transforms(root / scene.test)
    return holdout_split(train, scene.holdout_every)


def holdout_split(cams: list[Camera], k: int) -> tuple[list[Camera], list[Camera]]:
    """(train, test) of one list of cameras: every k-th is a test view, and not trained on."""
    return [c for i, c in enumerate(cams) if i % k], cams[::k]


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
    return image_path(root, cam.file_path, suffix)


def image_path(root: Path, rel: str, suffix: str) -> Path:
    """An image named relative to root, with `suffix` where it is named without one."""
    p = Path(root) / rel
    return p if p.suffix.lower() in IMAGE_SUFFIXES else p.with_name(p.name + suffix)


def read_frame_image(path: Path, cam: Camera, chroma: str = "decoded"):
    """A frame's linear image (times its exposure and white balance), the loss weight of
    each pixel (0 where the photograph clipped: its radiance is unknown), checked against its
    camera, and its alpha (None without one); chroma as imageio.read_photo's."""
    img, clipped, alpha = read_frame_rgba(path, chroma)
    if img.shape[:2] != (cam.height, cam.width):
        raise ClrefractError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]} but its "
            f"camera says {cam.width}x{cam.height}"
        )
    if not np.isfinite(img).all():
        raise ClrefractError(f"{path}: image has NaN or infinite pixels")
    check_background(path, img, alpha)
    weight = np.ones(img.shape[:2], np.float32)
    if clipped is not None:
        weight[clipped] = 0.0
    return img * frame_gain(cam), weight, alpha


def frame_gain(cam: Camera) -> np.ndarray:
    """(3,) what a frame's decoded values are multiplied by: its exposure and white balance."""
    return np.float32(cam.exposure) * np.asarray(cam.white_balance, np.float32)


def check_background(path: Path, img: np.ndarray, alpha: np.ndarray | None) -> None:
    """Refuse a frame whose background was cut away (NeRF-synthetic RGBA: alpha 0 over one
    flat colour, usually black). The loss compares every pixel with the environment seen
    through it, so a frame must show the environment; a photograph over it never holds
    one flat colour wherever its alpha is 0 (there the alpha is only a matte)."""
    if alpha is None:
        return
    clear = alpha <= 0
    if clear.mean() < 0.01:
        return
    under = img[clear]
    if np.ptp(under, axis=0).max() == 0:
        raise ClrefractError(
            f"{path}: transparent background ({100 * clear.mean():.0f}% of the pixels have "
            "alpha 0 and hold no picture): frames must show the environment behind the "
            "object; render or photograph them with it (their alpha then serves as the mask)"
        )


def alpha_mask(alpha: np.ndarray | None) -> np.ndarray | None:
    """The object mask of a frame's alpha (alpha > 0.5: the object) where the alpha varies;
    None where it is constant (an opaque frame says nothing of the object)."""
    if alpha is None or alpha.min() == alpha.max():
        return None
    return alpha > 0.5


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


MASK_DIR = "masks"


def mask_file(root: Path, cam: Camera, k: int) -> Path | None:
    """The user's object mask of frame k of its split: its mask_path, else masks/<frame>.png
    (or any image type) in the dataset folder, named after the frame's file (view_<k> for a
    frame without one); None without one."""
    if cam.mask_path:
        return image_path(root, cam.mask_path, ".png")
    stem = frame_stem(cam, k)
    return next(
        (p for s in IMAGE_SUFFIXES if (p := Path(root) / MASK_DIR / f"{stem}{s}").is_file()),
        None,
    )


def read_mask(path: Path, cam: Camera) -> np.ndarray:
    """A mask image as (H, W) bool: above half grey in its first channel, or where its alpha
    channel (if it varies) is above half."""
    from .imageio import read_pillow

    raw = read_pillow(path, "mask", "mask image")
    if raw.ndim == 3:  # alpha where it varies (a cut-out), else the grey level
        varies = raw.shape[2] in (2, 4) and raw[..., -1].min() != raw[..., -1].max()
        raw = raw[..., -1] if varies else raw[..., 0]
    if raw.shape != (cam.height, cam.width):
        raise ClrefractError(
            f"{path}: mask is {raw.shape[-1]}x{raw.shape[0]} but its camera says "
            f"{cam.width}x{cam.height}"
        )
    return raw > np.iinfo(raw.dtype).max / 2 if raw.dtype.kind == "u" else raw > 0.5


class Dataset:
    """A dataset folder: scene, cameras, images (read on demand) and environment map."""

    def __init__(self, root, box: Box | None = None):
        """`box` (e.g. from --box) replaces the scene's box and the one taken from the
        cameras."""
        self.root = Path(root)
        if not self.root.is_dir():
            raise ClrefractError(f"{self.root}: dataset folder not found")
        self.scene = read_scene(self.root)
        self.train, self.test = load_cameras(self.root, self.scene)
        if box is not None:
            self.scene.box = box
        if self.scene.box is None:
            self.scene.box = box_from_cameras(self.train + self.test, str(self.root))
        self.suffix = self.scene.frames or frame_suffix(self.root, self.train + self.test)
        for cam in self.train:  # before a run folder is touched: the start reads them late
            if cam.mask_path and not image_path(self.root, cam.mask_path, ".png").is_file():
                raise ClrefractError(f"{self.root / cam.mask_path}: mask file not found")
        self._weights: dict[str, np.ndarray] = {}
        self._alpha_masks: dict[int, np.ndarray | None] = {}
        # "stored": 4:2:0 JPEG training frames' colour as their blocks stored it (what the
        # srgb420 loss compares); test frames stay as decoded, as `eval` scores them
        self.train_chroma = "decoded"

    @property
    def box(self) -> Box:
        return self.scene.box

    def frames(self) -> list[tuple[Path, int, Camera]]:
        """Every frame once, in its file's order: (its transforms file, its place in that
        file's frames, its camera), the camera being the one `train` or `test` holds."""
        train, test = self.root / self.scene.train, self.root / self.scene.test
        if test != train:
            return [(train, k, c) for k, c in enumerate(self.train)] + [
                (test, k, c) for k, c in enumerate(self.test)
            ]
        every, n = self.scene.holdout_every, len(self.train) + len(self.test)
        # holdout_split's order: every k-th frame a test view, the rest training views
        return [
            (train, i, self.test[i // every] if i % every == 0 else self.train[i - i // every - 1])
            for i in range(n)
        ]

    def envmap(self) -> EnvMap:
        return EnvMap.from_file(self.root / self.scene.envmap, self.scene.envmap_matrix())

    def frame_path(self, cam: Camera) -> Path:
        return frame_image_path(self.root, cam, self.suffix)

    def frame(self, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Linear image (H, W, 3) and per-pixel loss weights (H, W) of a frame."""
        chroma = self.train_chroma if any(c is cam for c in self.train) else "decoded"
        img, weight, alpha = read_frame_image(self.frame_path(cam), cam, chroma)
        self._alpha_masks[id(cam)] = alpha_mask(alpha)  # read once: masks come from it too
        return img, weight

    def image(self, cam: Camera) -> np.ndarray:
        return self.frame(cam)[0]

    def chroma_halved(self) -> bool:
        """Whether every training frame is a JPEG with 4:2:0 chroma (the srgb420 loss's)."""
        return all(chroma_halved(self.frame_path(cam)) for cam in self.train)

    def _index(self, cam: Camera) -> int:
        """The frame's place in its split (names the masks of frames without a file)."""
        for split in (self.train, self.test):
            for k, c in enumerate(split):
                if c is cam:
                    return k
        return 0

    def mask_path(self, cam: Camera) -> Path | None:
        """The user's object mask file of a frame (see mask_file); None without one."""
        return mask_file(self.root, cam, self._index(cam))

    def _alpha_mask(self, cam: Camera) -> np.ndarray | None:
        if id(cam) not in self._alpha_masks:
            alpha = read_frame_rgba(self.frame_path(cam))[2]
            self._alpha_masks[id(cam)] = alpha_mask(alpha)
        return self._alpha_masks[id(cam)]

    def has_mask(self, cam: Camera) -> bool:
        return self.mask_path(cam) is not None or self._alpha_mask(cam) is not None

    def mask(self, cam: Camera) -> np.ndarray:
        """(H, W) bool object mask of a frame (white, or opaque alpha: the object): its mask
        file, else the frame's own alpha channel where that varies."""
        path = self.mask_path(cam)
        if path is not None:
            return read_mask(path, cam)
        mask = self._alpha_mask(cam)
        if mask is None:
            raise ClrefractError(f"{self.root}: frame {cam.name} has no mask")
        if mask.shape != (cam.height, cam.width):
            raise ClrefractError(
                f"{self.frame_path(cam)}: image is {mask.shape[1]}x{mask.shape[0]} but its "
                f"camera says {cam.width}x{cam.height}"
            )
        return mask

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


def _splits(root: Path, scene: Scene, problems: list[str]) -> list[tuple[str, list[Camera]]]:
    """(transforms file, cameras) of each split that could be read; the others' problems."""
    loaded = {}
    for name in dict.fromkeys([scene.train, scene.test]):
        try:
            loaded[name] = load_transforms(root / name)
        except ClrefractError as exc:
            problems.append(str(exc))
    if scene.train == scene.test and scene.train in loaded:
        train, test = load_cameras(root, scene)
        return [(scene.train, train), (scene.test, test)]
    return [(name, loaded[name]) for name in (scene.train, scene.test) if name in loaded]


def _describe_box(
    scene: Scene, cams: list[Camera], root: Path, notes: list[str], box: Box | None
) -> None:
    """Fill in the box (--box, else the cameras' where scene.json has none), saying where it
    came from, and doubt one too small for mm."""
    source = None
    if box is not None:
        scene.box, source = box, "--box"
    elif scene.box is None:
        scene.box, source = box_from_cameras(cams, str(root)), "the cameras"
    if source:
        lo = ", ".join(f"{x:.4g}" for x in scene.box.lo)
        hi = ", ".join(f"{x:.4g}" for x in scene.box.hi)
        notes.append(f"box from {source}: [{lo}] to [{hi}] mm, margin {scene.box.margin:.3g}")
    size = float(np.min(scene.box.size))
    if size < 10:
        notes.append(
            f"the box is only {size:.3g} mm across: are the camera poses in millimetres? "
            "(`clrefract dataset import --scale` converts them)"
        )


def _describe_footprint(cams, centre, size, notes: list[str]) -> None:
    """What the photographs resolve at the object, and the grid `fit --grid-res 0` picks for it."""
    from .resolution import cells_for, pixel_footprint_mm

    try:
        foot = pixel_footprint_mm(cams, centre)
    except ClrefractError:
        return  # cameras at the box centre: reported below
    notes.append(
        f"one pixel spans {foot:.2f} mm at the box centre: `fit --grid-res 0` gives "
        f"{cells_for(float(np.max(size)), foot)} cells across the box"
    )


def check_dataset(root, notes: list[str] | None = None, box: Box | None = None) -> list[str]:
    """Every problem found in a dataset folder, as messages naming the file (empty: fine).
    `notes` receives what was assumed for lack of a scene.json or of some of its keys;
    `box` (--box) replaces the scene's."""
    root = Path(root)
    problems: list[str] = []
    notes = [] if notes is None else notes
    if not root.is_dir():
        return [f"{root}: dataset folder not found"]
    try:
        scene = read_scene(root)
    except ClrefractError as exc:
        return [str(exc)]
    notes.extend(f"assumed {a}" for a in scene.assumed if box is None or "box" not in a)
    env = None
    try:
        env = EnvMap.from_file(root / scene.envmap, scene.envmap_matrix())
    except ClrefractError as exc:
        problems.append(str(exc))
    splits = _splits(root, scene, problems)
    try:
        _describe_box(scene, [c for _, cams in splits for c in cams], root, notes, box)
    except ClrefractError as exc:
        return problems + [str(exc)]
    lo, hi = np.asarray(scene.box.lo), np.asarray(scene.box.hi)
    centre, half = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    _describe_footprint([c for _, cams in splits for c in cams], centre, hi - lo, notes)
    from .box_walls import pick_views

    carved = set(pick_views(sum(len(cams) for _, cams in splits)))  # by place in the splits
    views: list[tuple[Camera, np.ndarray]] = []  # the views carved and their masks
    first = 0  # the place of the split's first frame
    for split, cams in splits:
        suffix = scene.frames or frame_suffix(root, cams)
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
            mask = mask_file(root, cam, k)
            if mask is not None:
                try:
                    read_mask(mask, cam)
                except ClrefractError as exc:
                    problems.append(str(exc))
            path = frame_image_path(root, cam, suffix)
            if not path.is_file():
                problems.append(f"{where}: image {path} is missing")
                continue
            try:
                img, _, alpha = read_frame_rgba(path)
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
            try:
                check_background(path, img, alpha)
            except ClrefractError as exc:
                problems.append(str(exc))
            if first + k in carved and env is not None and not problems:
                views.append((cam, _view_mask(mask, cam, img, alpha, env)))
        first += len(cams)
    if not problems:
        _describe_walls(scene.box, views, notes)
    return problems


def _view_mask(path: Path | None, cam: Camera, img, alpha, env: EnvMap) -> np.ndarray:
    """A frame's mask as a fit takes it: its mask file, else its alpha where that varies,
    else the pixels that differ from the straight view of the environment."""
    from .hull import refraction_mask

    if path is not None:
        return read_mask(path, cam)
    mask = alpha_mask(alpha)
    return refraction_mask(cam, img * frame_gain(cam), env) if mask is None else mask


def _describe_walls(box: Box, views: list, notes: list[str]) -> None:
    """Warn where the masks' hull reaches the box's walls (box_walls), with a box to give."""
    from .box_walls import box_walls

    if not views:
        return
    walls = box_walls(box, [c for c, _ in views], [m for _, m in views])
    if walls is not None:
        notes.append(f"warning: {walls.message()}")
