"""`clrefract dataset make --realistic`: a synthetic capture with the flaws of a real one.

The scene is rendered as a photographer with a calibrated camera would have shot it: through
an OPENCV lens, from poses that the transforms file records a little wrong, on a noisy sensor
developed to 8-bit sRGB JPEG, at an exposure and white balance that wander from view to view,
in front of a panorama turned by a few degrees. The dataset records what such a photographer
would know (the lens, the poses as estimated, the nominal exposure); the truth the fit is
not told goes to `realistic.json` beside it, to score estimates against:

    flaws, seed             the settings it was made with
    nominal_exposure        camera value of radiance 1 (frames record 1 / it: exposure_scale)
    clipped_pixels          the share of pixels developed to 254 or more (before the JPEG)
    envmap_rotation(_matrix)  the panorama's true turn, as scene.json's envmap_rotation
    frames[]                per view: the true and the recorded transform_matrix, the
                            exposure jitter exposure_ev, the red and blue `tint`, their
                            product `gains` (a frame as the loader reads it = gains x
                            radiance + noise), and the exposure_scale and white_balance
                            that would undo them in a transforms file
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from scipy.spatial.transform import Rotation

from .cameras import Camera, load_transforms, save_transforms
from .envmap import EnvMap, rotation_matrix
from .errors import ClrefractError
from .imageio import atomic_path, linear_to_srgb, write_exr_rgb, write_png_srgb

TRUTH_FILE = "realistic.json"
_SALT = 0x5EA1  # keeps the flaws' random streams apart from the panorama's, same seed
_SUBSAMPLING = {444: 0, 422: 1, 420: 2}  # Pillow's codes


@dataclass
class Flaws:
    """A real capture's flaws. Flaws() is `--realistic`; Flaws.none() has every flaw off."""

    k1: float = -0.05  # OPENCV lens, recorded in the transforms files
    k2: float = 0.01
    p1: float = 0.001
    p2: float = 0.001
    pose_deg: float = 0.1  # recorded poses turned by this much about a random axis
    pose_mm: float = 0.2  # and moved by this much in a random direction
    full_well: float = 4000.0  # photo-electrons at full scale (Poisson); 0: no shot noise
    read_noise: float = 0.001  # Gaussian, in units of full scale; 0: none
    jpeg: int = 90  # quality of the 8-bit sRGB JPEG frames; 0: linear EXR frames
    chroma: int = 420  # the JPEG's chroma subsampling: 420 (Pillow's, phones'), 422 or 444
    exposure_ev: float = 0.3  # per-view exposure uniform in +-this, not recorded
    tint: float = 0.03  # per-view red and blue gains uniform in 1 +- this, not recorded
    env_rotation: tuple[float, float, float] = (3.0, -2.0, 4.0)  # panorama's turn, degrees
    clip: float = 0.02  # share of the panorama allowed to clip at the brightest view

    @classmethod
    def none(cls) -> Flaws:
        off = dict(k1=0.0, k2=0.0, p1=0.0, p2=0.0, pose_deg=0.0, pose_mm=0.0, full_well=0.0)
        off.update(read_noise=0.0, jpeg=0, exposure_ev=0.0, tint=0.0, env_rotation=(0.0,) * 3)
        return cls(**off)

    @property
    def distortion(self) -> dict:
        return {k: v for k in ("k1", "k2", "p1", "p2") if (v := getattr(self, k)) != 0.0}

    @property
    def sensor(self) -> bool:
        """Whether frames are developed from a sensor's values (noise or 8 bits), which
        needs an exposure that keeps the picture below full scale."""
        return self.jpeg > 0 or self.full_well > 0 or self.read_noise > 0

    def check(self, camera: Camera) -> None:
        """ClrefractError, in one line, for a value out of range or a lens that folds the
        camera's image."""
        bad = [
            (self.pose_deg >= 0 and self.pose_mm >= 0, "pose_deg and pose_mm must be >= 0"),
            (self.full_well >= 0 and self.read_noise >= 0, "noise must be >= 0"),
            (self.jpeg == 0 or 1 <= self.jpeg <= 100, "jpeg must be a quality 1 to 100, or 0"),
            (self.chroma in _SUBSAMPLING, "chroma must be 420, 422 or 444"),
            (0 <= self.exposure_ev <= 4, "exposure_ev must be 0 to 4"),
            (0 <= self.tint < 0.5, "tint must be 0 to 0.5"),
            (0 < self.clip < 0.5, "clip must be above 0 and below 0.5"),
        ]
        for ok, why in bad:
            if not ok:
                raise ClrefractError(f"--realistic: {why}")
        if not self.distortion:
            return
        # the loader's own check of the lens, on the transforms file it would read
        with tempfile.TemporaryDirectory() as tmp:
            lens = dataclasses.replace(camera, camera_model="OPENCV", distortion=self.distortion)
            save_transforms(Path(tmp) / "lens.json", [lens])
            try:
                load_transforms(Path(tmp) / "lens.json")
            except ClrefractError as exc:
                why = str(exc).split("folds the image", 1)[-1].strip(" ()")
                raise ClrefractError(
                    f"--realistic: the lens {self.distortion} folds the image ({why})"
                ) from None


def parse_flaws(spec: str, base: Flaws | None = None) -> Flaws:
    """Flaws from KEY=VALUE,... (vectors with '/': env_rotation=3/-2/4) over `base`
    (default: every flaw off); ClrefractError naming the option for a bad key or value."""
    flaws = base if base is not None else Flaws.none()
    names = {f.name: f for f in dataclasses.fields(Flaws)}
    for item in filter(None, (w.strip() for w in spec.split(","))):
        key, sep, value = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in names:
            raise ClrefractError(
                f"--flaws: {item!r} is not KEY=VALUE with KEY one of {', '.join(names)}"
            )
        try:
            if key == "env_rotation":
                parsed = tuple(float(v) for v in value.split("/"))
                if len(parsed) != 3 or not np.isfinite(parsed).all():
                    raise ValueError
            elif key in ("jpeg", "chroma"):
                parsed = int(value)
            else:
                parsed = float(value)
                if not np.isfinite(parsed):
                    raise ValueError
        except ValueError:
            want = "RX/RY/RZ degrees" if key == "env_rotation" else "a number"
            raise ClrefractError(f"--flaws: {key} must be {want}, got {value!r}") from None
        flaws = dataclasses.replace(flaws, **{key: parsed})
    return flaws


def nominal_exposure(panorama: np.ndarray, flaws: Flaws) -> float:
    """Camera value of radiance 1: the brightest view (top exposure and tint) clips no more
    than `clip` of the panorama's solid angle, as a photographer would meter it."""
    if not flaws.sensor:
        return 1.0
    peak = panorama.max(axis=-1)
    h = peak.shape[0]
    solid = np.broadcast_to(np.sin((np.arange(h) + 0.5) / h * np.pi)[:, None], peak.shape)
    order = np.argsort(peak, axis=None)
    share = np.cumsum(solid.ravel()[order])
    level = float(peak.ravel()[order][np.searchsorted(share, (1 - flaws.clip) * share[-1])])
    top_gain = 2.0**flaws.exposure_ev * (1.0 + flaws.tint)
    return 1.0 / (max(level, 1e-12) * top_gain)


class RealisticCapture:
    """Renders views as a flawed camera would record them; collects the truth as it goes.

    `env` is the panorama the fit is given; `self.env` the one turned by the flaws' rotation,
    which the views are rendered with."""

    def __init__(self, flaws: Flaws, env: EnvMap, seed: int):
        self.flaws, self.seed = flaws, int(seed)
        turn = rotation_matrix(list(flaws.env_rotation))
        base = np.eye(3) if env.rotation is None else env.rotation
        self.env = EnvMap(env.image, turn @ base)
        self.exposure = nominal_exposure(env.image, flaws)
        self.frames: list[dict] = []
        self.clipped = 0
        self.pixels = 0

    def lens(self, cam: Camera) -> Camera:
        """The camera with the flaws' lens: rays leave through it, and the transforms file
        records it."""
        model = "OPENCV" if self.flaws.distortion else cam.camera_model
        return dataclasses.replace(cam, camera_model=model, distortion=self.flaws.distortion)

    def rng(self, k: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, _SALT, k])

    def shoot(self, k: int, cam: Camera, radiance: np.ndarray, stem: Path, split: str) -> Camera:
        """Develop view k's radiance (H, W, 3, rendered from cam's true pose) into
        stem.jpg (or stem.exr), and return the camera the transforms file records."""
        f = self.flaws
        rng = self.rng(k)
        ev = rng.uniform(-f.exposure_ev, f.exposure_ev)
        red_blue = 1.0 + rng.uniform(-f.tint, f.tint, 2)
        white = np.array([red_blue[0], 1.0, red_blue[1]])
        gains = 2.0**ev * white
        value = np.clip(radiance * (self.exposure * gains), 0.0, None)
        if f.full_well > 0:
            value = rng.poisson(value * f.full_well) / f.full_well
        if f.read_noise > 0:
            value = value + rng.normal(0.0, f.read_noise, value.shape)
        recorded = dataclasses.replace(
            cam,
            c2w=perturb_pose(cam.c2w, f.pose_deg, f.pose_mm, rng),
            exposure=1.0 / self.exposure,
        )
        if f.jpeg > 0:
            path = stem.with_suffix(".jpg")
            encoded = np.round(linear_to_srgb(value) * 255.0).astype(np.uint8)
            self.clipped += int((encoded >= 254).any(axis=-1).sum())
            with atomic_path(path, suffix=".jpg") as tmp:
                iio.imwrite(
                    tmp,
                    encoded,
                    extension=".jpg",
                    quality=int(f.jpeg),
                    subsampling=_SUBSAMPLING[f.chroma],
                )
        else:
            path = stem.with_suffix(".exr")
            write_exr_rgb(path, value.astype(np.float32))
            write_png_srgb(stem.with_suffix(".png"), value)
        self.pixels += cam.width * cam.height
        recorded.file_path = f"./{split}/{path.name}"
        # what a transforms file would need to undo them: white balance with a geometric
        # mean of 1, as `dataset register-env --exposure` writes it
        undo = 1.0 / (self.exposure * gains)
        balance = np.exp(np.log(undo).mean())
        self.frames.append(
            {
                "file_path": recorded.file_path,
                "transform_matrix": cam.c2w.tolist(),
                "recorded_transform_matrix": recorded.c2w.tolist(),
                "exposure_ev": float(ev),
                "tint": white.tolist(),
                "gains": gains.tolist(),
                "exposure_scale": float(balance),
                "white_balance": (undo / balance).tolist(),
            }
        )
        return recorded

    def summary(self) -> dict:
        return {
            "nominal_exposure": self.exposure,
            "clipped_pixels": self.clipped / max(self.pixels, 1),
        }

    def save(self, out: Path) -> None:
        """Write realistic.json: the flaws and every truth the dataset does not record."""
        turn = np.eye(3) if self.env.rotation is None else self.env.rotation
        truth = {
            "flaws": dataclasses.asdict(self.flaws),
            "seed": self.seed,
            **self.summary(),
            "envmap_rotation": Rotation.from_matrix(turn).as_euler("xyz", degrees=True).tolist(),
            "envmap_rotation_matrix": turn.tolist(),
            "frames": self.frames,
        }
        with atomic_path(Path(out) / TRUTH_FILE, suffix=".json") as tmp:
            tmp.write_text(json.dumps(truth, indent=2) + "\n", encoding="utf-8")


def perturb_pose(c2w: np.ndarray, degrees: float, mm: float, rng) -> np.ndarray:
    """c2w turned by exactly `degrees` about a random axis through the camera, and moved by
    exactly `mm` in a random direction."""
    axis, shift = rng.normal(size=(2, 3))
    axis /= np.linalg.norm(axis)
    shift /= np.linalg.norm(shift)
    out = np.array(c2w, dtype=np.float64)
    out[:3, :3] = Rotation.from_rotvec(np.radians(degrees) * axis).as_matrix() @ out[:3, :3]
    out[:3, 3] += mm * shift
    return out


def pose_error(true: np.ndarray, recorded: np.ndarray) -> tuple[float, float]:
    """(degrees, mm) between two camera-to-world matrices: the angle of the rotation that
    takes one onto the other, and the distance between the camera centres."""
    turn = np.asarray(recorded)[:3, :3] @ np.asarray(true)[:3, :3].T
    deg = float(np.degrees(Rotation.from_matrix(turn).magnitude()))
    return deg, float(np.linalg.norm(np.asarray(recorded)[:3, 3] - np.asarray(true)[:3, 3]))


def load_truth(root: Path) -> dict:
    """realistic.json of a dataset folder; ClrefractError naming it if absent or unreadable."""
    path = Path(root) / TRUTH_FILE
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ClrefractError(
            f"{path}: cannot read the truth of a realistic dataset ({exc})"
        ) from None
