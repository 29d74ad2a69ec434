"""`clrefract dataset import`: a capture in the layouts people have, made a dataset folder.

    NeRF synthetic (Blender):  SRC/transforms_train.json, transforms_test.json (and _val,
                               not used), frames ./train/r_0 meaning r_0.png
    instant-ngp / COLMAP:      SRC/transforms.json; every 8th frame becomes a test view, and
                               its aabb_scale, scale and offset give the box (ngp_box)
    COLMAP sparse model:       SRC/sparse/0, SRC/sparse or SRC with cameras, images and
                               points3D (.bin or .txt), images in SRC/images (colmap.py);
                               its world is turned so that up is +z (--up)
Poses are multiplied by --scale (or the scale --known-distance gives) into millimetres, frames
and masks (masks/<frame>.png, or in a COLMAP project COLMAP's masks/<image name>.png) are
copied beside the new transforms files, and scene.json records the box
(--pose-box, else instant-ngp's, else a COLMAP model's sparse points, else the region the
cameras look at), the index range and where the capture came from. Nothing in an existing
dataset is replaced.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

from .cameras import IMAGE_SUFFIXES, Camera, load_transforms, save_transforms
from .colmap import (
    ColmapCapture,
    Levelling,
    box_from_points,
    euler_degrees,
    find_model,
    level_capture,
    model_file,
    parse_up,
    read_colmap,
    split_by_name,
)
from .dataset import (
    DEFAULT_ETA_RANGE,
    DEFAULT_HOLDOUT,
    MASK_DIR,
    SCENE_FILE,
    Scene,
    box_from_cameras,
    box_of,
    default_margin,
    finite_numbers,
    frame_suffix,
    holdout_split,
    mask_file,
    write_scene,
)
from .envmap import EnvMap, rotation_matrix
from .errors import ClrefractError
from .fields.base import Box
from .imageio import HDR_SUFFIXES, ensure_out_dir

WRITES = (SCENE_FILE, "transforms_train.json", "transforms_test.json")


def _layout(src: Path) -> tuple[str, list[Camera], list[Camera], Path | None]:
    """(layout name, train cameras, test cameras, the single transforms file or None) of a
    capture folder or transforms file."""
    if src.is_file():
        src, single = src.parent, src.name
    elif (src / "transforms_train.json").is_file():
        train = load_transforms(src / "transforms_train.json")
        test_file = src / "transforms_test.json"
        if test_file.is_file():
            return "nerf-synthetic", train, load_transforms(test_file), None
        return "nerf-synthetic", *holdout_split(train, DEFAULT_HOLDOUT), None
    elif (src / "transforms.json").is_file():
        single = "transforms.json"
    elif not src.exists():
        raise ClrefractError(f"{src}: capture folder not found")
    else:
        raise ClrefractError(
            f"{src}: no transforms_train.json, transforms.json or COLMAP model here (a "
            "NeRF-synthetic, instant-ngp or COLMAP capture: sparse/0, sparse or this folder "
            "holding cameras.bin or cameras.txt)"
        )
    cams = load_transforms(src / single)
    if len(cams) < 2:
        raise ClrefractError(f"{src / single}: need at least 2 frames, found {len(cams)}")
    # as a dataset folder with only transforms.json splits it
    return "instant-ngp", *holdout_split(cams, DEFAULT_HOLDOUT), src / single


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


# instant-ngp's defaults (nerf_loader.cu: NERF_SCALE, offset 0.5, aabb_scale 1)
NGP_KEYS = {"scale": 0.33, "offset": [0.5, 0.5, 0.5], "aabb_scale": 1}


def _ngp_keys(path: Path) -> dict | None:
    """aabb_scale, scale and offset of an instant-ngp transforms.json (instant-ngp's default
    for each one missing); None where it sets none of them."""
    top = json.loads(path.read_text(encoding="utf-8"))  # load_transforms read it already
    if not any(k in top for k in NGP_KEYS):
        return None
    keys = {k: top.get(k, v) for k, v in NGP_KEYS.items()}
    if finite_numbers([keys["offset"]], 1):  # one number: the same on every axis
        keys["offset"] = [keys["offset"]] * 3
    sizes = [keys["scale"], keys["aabb_scale"]]
    if not (finite_numbers(sizes, 2) and min(sizes) > 0 and finite_numbers(keys["offset"], 3)):
        raise ClrefractError(
            f"{path}: 'scale' and 'aabb_scale' must be positive numbers and 'offset' a number "
            f"or 3 numbers, got {[top.get(k) for k in NGP_KEYS]}"
        )
    return keys


def ngp_box(keys: dict, cams: list[Camera], scale: float, where: str) -> tuple[Box, str]:
    """instant-ngp's box in the poses' units times `scale` (mm). instant-ngp maps a position p
    of transforms.json to p * scale + offset (then cycles the axes, which a cube centred on
    (0.5, 0.5, 0.5) does not see) and traces the cube of side aabb_scale about (0.5, 0.5, 0.5)
    (docs/nerf_dataset_tips.md, nerf_loader.h); so p spans (0.5 -+ aabb_scale / 2 - offset)
    / scale. aabb_scale > 1 takes in the background, which here is the environment map: where
    that cube holds a camera, the unit cube (aabb_scale 1, the object of interest) is used."""
    off = np.asarray(keys["offset"], float)
    eyes = np.array([c.c2w[:3, 3] for c in cams])
    for a in dict.fromkeys([float(keys["aabb_scale"]), 1.0]):
        lo = (0.5 - a / 2 - off) / keys["scale"] * scale
        hi = (0.5 + a / 2 - off) / keys["scale"] * scale
        if not np.any(np.all((eyes > lo) & (eyes < hi), axis=1)):
            return Box(
                tuple(lo), tuple(hi), default_margin(lo, hi)
            ), f"instant-ngp aabb_scale {a:g}"
    raise ClrefractError(
        f"{where}: instant-ngp's box (scale {keys['scale']}, offset {keys['offset']}, even at "
        "aabb_scale 1) holds cameras; give the object's box with --pose-box"
    )


def _colmap(src: Path, images: Path | None) -> ColmapCapture | None:
    """The COLMAP project src, None where src is a transforms capture (those come first)."""
    transforms = ("transforms_train.json", "transforms.json")
    model = None
    if src.is_dir() and not any((src / f).is_file() for f in transforms):
        model = find_model(src)
    if model is None:
        if images is not None:
            raise ClrefractError(f"{src}: --images is for a COLMAP project, and this is none")
        return None
    return read_colmap(src, model, images)


def camera_named(cams: list[Camera], name: str, where: str) -> Camera:
    """The camera of the image called `name`: the one so named, else the only one whose file
    name (with or without its image type) is `name`'s."""

    def key(n: str) -> str:
        p = Path(n)
        return p.stem if p.suffix.lower() in IMAGE_SUFFIXES else p.name

    found = [c for c in cams if c.name == name] or [c for c in cams if key(c.name) == key(name)]
    if len(found) != 1:
        some = f"names {len(found)} images ({', '.join(c.name for c in found[:4])})"
        raise ClrefractError(
            f"{where}: --known-distance: {'no image is' if not found else some} named {name!r}"
        )
    return found[0]


def known_distance_scale(cams: list[Camera], first: str, second: str, mm, where: str) -> float:
    """Millimetres per unit of the poses that put the centres of the images named `first`
    and `second` `mm` apart."""
    try:
        mm = float(mm)
    except ValueError:
        raise ClrefractError(f"--known-distance: {mm!r} is not a number of mm") from None
    if not (mm > 0 and np.isfinite(mm)):
        raise ClrefractError(f"--known-distance: the distance must be positive mm, got {mm:g}")
    a, b = camera_named(cams, first, where), camera_named(cams, second, where)
    if a is b:
        raise ClrefractError(f"--known-distance: {first!r} and {second!r} name one image")
    units = float(np.linalg.norm(a.position - b.position))
    if not units > 0:
        raise ClrefractError(f"{where}: images {first!r} and {second!r} have the same centre")
    return mm / units


def import_capture(
    src: Path,
    out: Path,
    scale: float | None = None,
    box: list[float] | None = None,
    eta_range: tuple[float, float] = DEFAULT_ETA_RANGE,
    envmap: Path | None = None,
    env_rotation: list[float] | None = None,
    known_distance: tuple[str, str, float] | None = None,
    images: Path | None = None,
    up: str | None = None,
) -> dict:
    """Write a dataset folder `out` from a capture `src`; returns what was done. The scale is
    `scale` mm per unit, or the one `known_distance` (image, image, mm) gives, else 1; `images`
    is a COLMAP project's image folder (default src/images). A COLMAP model's world is turned
    so that up is +z (`up`: parse_up's 'auto', the default, 'keep' or 'X,Y,Z'; see
    level_capture); `env_rotation` and the sparse points are in the model's world, `box` in
    the turned one."""
    src, out = Path(src), Path(out)
    if scale is not None and known_distance is not None:
        raise ClrefractError("give --scale or --known-distance, not both")
    if scale is not None and not (scale > 0 and np.isfinite(scale)):
        raise ClrefractError(f"--scale must be a positive number (mm per unit), got {scale}")
    if not 1.0 <= eta_range[0] < eta_range[1]:
        raise ClrefractError(f"--eta-range must be lo hi with 1 <= lo < hi, got {eta_range}")
    up_spec = parse_up(up)
    capture = _colmap(src, images)
    level = None
    if capture is None and up is not None:
        raise ClrefractError(f"{src}: --up is for a COLMAP project, and this is none")
    if capture is not None:
        capture, level = level_capture(capture, up_spec)
        train, test, split_rule = split_by_name(capture.cameras, DEFAULT_HOLDOUT)
        layout, single, where = "colmap", None, str(model_file(capture.model, "images"))
    else:
        layout, train, test, single = _layout(src)
        split_rule, where = None, str(single or src)
    scale_from = "--scale" if scale is not None else "the default (1 mm per unit)"
    if known_distance is not None:
        scale = known_distance_scale(train + test, *known_distance, where)
        scale_from = "--known-distance {} {} {} mm".format(*known_distance)
    scale = 1.0 if scale is None else scale
    root = src if src.is_dir() else src.parent
    clash = [name for name in WRITES if (out / name).exists()]
    if clash:
        raise ClrefractError(
            f"{out}: already holds a dataset ({', '.join(clash)}); choose another --out"
        )
    if envmap:
        env = Path(envmap)
    else:
        env = next((e for e in (root / "envmap.exr", root / "envmap.hdr") if e.is_file()), None)
        env = env or root / "envmap.exr"
    if not env.is_file():
        raise ClrefractError(
            f"{env}: environment map not found; give the HDR panorama with --envmap"
        )
    if env_rotation is not None and not finite_numbers(env_rotation, 3):
        raise ClrefractError(f"--env-rotation must be three numbers (degrees), got {env_rotation}")
    if env_rotation is not None and level is not None and level.degrees > 0:
        # given in the model's world: it turns with the world
        env_rotation = euler_degrees(level.rotation @ rotation_matrix(env_rotation))
    EnvMap.from_file(env)  # a panorama that cannot be read is refused before any copy
    env_name = "envmap.hdr" if env.suffix.lower() in HDR_SUFFIXES else "envmap.exr"
    cams = {"train": [_scaled(c, scale) for c in train], "test": [_scaled(c, scale) for c in test]}
    everyone = cams["train"] + cams["test"]
    ngp = _ngp_keys(single) if single is not None else None
    if box is not None:
        the_box, box_source = box_of(box, scale, "--pose-box"), "--pose-box"
    elif ngp is not None:
        the_box, box_source = ngp_box(ngp, everyone, scale, str(single))
    elif capture is not None:
        points = str(model_file(capture.model, "points3D"))
        the_box, box_source = box_from_points(capture.points * scale, everyone, points)
    else:
        the_box, box_source = box_from_cameras(everyone, str(src)), "the cameras"
    ensure_out_dir(out, "dataset folder")
    hint = frame_suffix(root, train + test)
    for split in cams.values():
        for k, cam in enumerate(split):
            folder_mask = None if cam.mask_path else mask_file(root, cam, k)
            if capture is not None:  # images/<name> in both, the name as the model gives it
                (out / cam.file_path).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(capture.sources[cam.file_path], out / cam.file_path)
                # COLMAP's own naming, masks/<image name>.png, kept and named in the frame
                rel = Path(MASK_DIR) / f"{Path(cam.file_path).relative_to('images')}.png"
                if folder_mask is None and not cam.mask_path and (root / rel).is_file():
                    (out / rel).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(root / rel, out / rel)
                    cam.mask_path = rel.as_posix()
            else:
                cam.file_path = _copy_file(root, cam.file_path, out, hint)
            if cam.mask_path:
                cam.mask_path = _copy_file(root, cam.mask_path, out, ".png")
            elif folder_mask is not None:  # masks/<frame>: the same name beside the copy
                (out / MASK_DIR).mkdir(exist_ok=True)
                shutil.copyfile(folder_mask, out / MASK_DIR / folder_mask.name)
    shutil.copyfile(env, out / env_name)
    save_transforms(out / "transforms_train.json", cams["train"])
    save_transforms(out / "transforms_test.json", cams["test"])
    scene = Scene(
        box=the_box,
        eta_range=tuple(eta_range),
        envmap=env_name,
        envmap_rotation=None if env_rotation is None else [float(a) for a in env_rotation],
        frames=hint,
        extra={
            "import": {
                "source": str(src.resolve()),
                "layout": layout,
                "scale": scale,
                "scale_from": scale_from,
                "box_from": box_source,
                **({"model": str(capture.model.resolve()), "split": split_rule} if capture else {}),
                **(_up_record(level) if level else {}),
            }
        },
    )
    write_scene(out, scene)
    return {
        "layout": layout,
        "train": len(cams["train"]),
        "test": len(cams["test"]),
        "frames": hint,
        "box": the_box.to_dict(),
        "box_from": box_source,
        "scale": scale,
        "scale_from": scale_from,
        **({"split": split_rule} if split_rule else {}),
        **({"up_from": level.source, "up_turned_deg": round(level.degrees, 4)} if level else {}),
        **({"envmap_rotation": scene.envmap_rotation} if level and env_rotation else {}),
    }


def _up_record(level: Levelling) -> dict:
    """scene.json's record of a COLMAP model's levelling: where up came from, up in the
    model's world, the angle turned and the rotation from the model's world to the
    dataset's (before the scale)."""
    return {
        "up_from": level.source,
        "up_in_model": [round(float(x), 9) for x in level.up],
        "up_turned_deg": round(level.degrees, 4),
        "world_from_model": np.round(level.rotation, 12).tolist(),
    }
