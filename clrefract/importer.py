"""`clrefract dataset import`: a capture in the layouts people have, made a dataset folder.

    NeRF synthetic (Blender):  SRC/transforms_train.json, transforms_test.json (and _val,
                               not used), frames ./train/r_0 meaning r_0.png
    instant-ngp / COLMAP:      SRC/transforms.json (aabb_scale, scale and offset are
                               instant-ngp's own normalisation and are not used); every 8th
                               frame becomes a test view
Poses are multiplied by --scale into millimetres, frames and masks are copied beside the new
transforms files, and scene.json records the box (--box, else the region the cameras look at),
the index range and where the capture came from. Nothing in an existing dataset is replaced.
"""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

from .cameras import IMAGE_SUFFIXES, Camera, load_transforms, save_transforms
from .dataset import (
    DEFAULT_ETA_RANGE,
    DEFAULT_HOLDOUT,
    SCENE_FILE,
    Scene,
    box_from_cameras,
    default_margin,
    frame_suffix,
    holdout_split,
    write_scene,
)
from .errors import ClrefractError
from .fields.base import Box
from .imageio import ensure_out_dir

WRITES = (SCENE_FILE, "transforms_train.json", "transforms_test.json")


def _layout(src: Path) -> tuple[str, list[Camera], list[Camera]]:
    """(layout name, train cameras, test cameras) of a capture folder or transforms file."""
    if src.is_file():
        src, single = src.parent, src.name
    elif (src / "transforms_train.json").is_file():
        train = load_transforms(src / "transforms_train.json")
        test_file = src / "transforms_test.json"
        if test_file.is_file():
            return "nerf-synthetic", train, load_transforms(test_file)
        return "nerf-synthetic", *holdout_split(train, DEFAULT_HOLDOUT)
    elif (src / "transforms.json").is_file():
        single = "transforms.json"
    elif not src.exists():
        raise ClrefractError(f"{src}: capture folder not found")
    else:
        raise ClrefractError(
            f"{src}: no transforms_train.json or transforms.json here (a NeRF-synthetic or "
            "instant-ngp capture)"
        )
    cams = load_transforms(src / single)
    if len(cams) < 2:
        raise ClrefractError(f"{src / single}: need at least 2 frames, found {len(cams)}")
    # as a dataset folder with only transforms.json splits it
    return "instant-ngp", *holdout_split(cams, DEFAULT_HOLDOUT)


def _scaled(cam: Camera, scale: float) -> Camera:
    c2w = cam.c2w.copy()
    c2w[:3, 3] *= scale
    return replace(cam, c2w=c2w)


def _copy_file(src_root: Path, rel: str, out: Path, suffix_hint: str) -> str:
    """Copy a frame (or mask) named relative to src_root into out at the same relative
    place; returns its name there. Frames named without extension keep that form."""
    p = src_root / rel
    if p.suffix.lower() not in IMAGE_SUFFIXES:
        p = p.with_name(p.name + suffix_hint)
    if not p.is_file():
        raise ClrefractError(f"{p}: image named in the transforms file not found")
    dst = (out / rel).resolve()
    if not dst.is_relative_to(out.resolve()):  # '../x' or an absolute path: flatten it
        dst, rel = out / "frames" / p.name, f"frames/{p.name}"
    dst = dst if dst.suffix.lower() in IMAGE_SUFFIXES else dst.with_name(p.name)
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(p, dst)
    return rel


def _parse_box(values: list[float] | None, scale: float) -> Box | None:
    if values is None:
        return None
    lo, hi = np.array(values[:3]) * scale, np.array(values[3:]) * scale
    return Box(tuple(lo), tuple(hi), default_margin(lo, hi))


def import_capture(
    src: Path,
    out: Path,
    scale: float = 1.0,
    box: list[float] | None = None,
    eta_range: tuple[float, float] = DEFAULT_ETA_RANGE,
    envmap: Path | None = None,
) -> dict:
    """Write a dataset folder `out` from a capture `src`; returns what was done."""
    src, out = Path(src), Path(out)
    if not (scale > 0 and np.isfinite(scale)):
        raise ClrefractError(f"--scale must be a positive number (mm per unit), got {scale}")
    if not 1.0 <= eta_range[0] < eta_range[1]:
        raise ClrefractError(f"--eta-range must be lo hi with 1 <= lo < hi, got {eta_range}")
    layout, train, test = _layout(src)
    root = src if src.is_dir() else src.parent
    clash = [name for name in WRITES if (out / name).exists()]
    if clash:
        raise ClrefractError(
            f"{out}: already holds a dataset ({', '.join(clash)}); choose another --out"
        )
    env = Path(envmap) if envmap else root / "envmap.exr"
    if not env.is_file():
        raise ClrefractError(
            f"{env}: environment map not found; give the HDR panorama with --envmap"
        )
    ensure_out_dir(out, "dataset folder")
    hint = frame_suffix(root, train + test)
    cams = {"train": [_scaled(c, scale) for c in train], "test": [_scaled(c, scale) for c in test]}
    for split in cams.values():
        for cam in split:
            cam.file_path = _copy_file(root, cam.file_path, out, hint)
            if cam.mask_path:
                cam.mask_path = _copy_file(root, cam.mask_path, out, ".png")
    the_box = _parse_box(box, scale) or box_from_cameras(cams["train"] + cams["test"], str(src))
    shutil.copyfile(env, out / "envmap.exr")
    save_transforms(out / "transforms_train.json", cams["train"])
    save_transforms(out / "transforms_test.json", cams["test"])
    scene = Scene(
        box=the_box,
        eta_range=tuple(eta_range),
        frames=hint,
        extra={"import": {"source": str(src.resolve()), "layout": layout, "scale": scale}},
    )
    write_scene(out, scene)
    return {
        "layout": layout,
        "train": len(cams["train"]),
        "test": len(cams["test"]),
        "frames": hint,
        "box": the_box.to_dict(),
        "scale": scale,
    }
