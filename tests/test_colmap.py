"""COLMAP projects: a dataset exported to a COLMAP model in a random similarity imports back to
the same cameras (scale from --known-distance, --up keep), each COLMAP camera model gives the
rays pycolmap gives, the box comes from the sparse points, a tilted model is levelled (its up
turned to +z, from the cameras or --up) and bad input is refused in one line."""

import json
import re
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap  # the `test` extra installs it
import pytest
from scipy.spatial.transform import Rotation

from clrefract.calibrate import calibrate, rotation_angle
from clrefract.cameras import Camera, fibonacci_sphere_cameras, look_at, orbit_cameras
from clrefract.cli import main
from clrefract.colmap import (
    READ_MODELS,
    add_camera,
    add_posed_image,
    colmap_from_c2w,
    estimate_up,
    export_colmap,
    read_colmap,
)
from clrefract.dataset import Dataset
from clrefract.errors import ClrefractError
from clrefract.imageio import write_png
from clrefract.synth import MakeOptions, make_dataset

RADIUS = 20.0  # mm: the sphere scene's object, centred on the origin
SCALE = 1 / 37  # model units per mm of the random similarity
# the tilted model's similarity: 70 degrees about an oblique axis tilts up by 68
AXIS = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
TILT = Rotation.from_rotvec(np.radians(70.0) * AXIS).as_matrix()
SHIFT = np.array([0.4, -1.1, 2.3])  # model units
SEMI_AXES = np.array([8.0, 8.0, 25.0])  # mm: a tall ellipsoid of sparse points
Z = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sphere")
    make_dataset("sphere", out, MakeOptions(views=16, res=32, env_width=256, volume_res=12))
    return out


def _distance(ds: Dataset, a: str, b: str) -> float:
    pos = {Path(c.file_path).stem: c.position for c in ds.train + ds.test}
    return float(np.linalg.norm(pos[Path(a).stem] - pos[Path(b).stem]))


def _refused(capsys, argv: list[str], *words: str) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("clrefract: error: "), err
    for w in words:
        assert w in err, (w, err)
    return err


@pytest.mark.parametrize("text", [False, True], ids=["binary", "text"])
def test_similarity_is_undone(dataset, tmp_path, capsys, text):
    rng = np.random.default_rng(7 + text)
    rot = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
    shift = rng.normal(0.0, 3.0, 3)  # model units
    proj = tmp_path / "proj"
    info = export_colmap(dataset, proj, text=text, similarity=(SCALE, rot, shift))
    assert info["points"] > 1000 and info["images"] == 16
    # a real model's points also lie far off (the room) and a few stray about the object
    model = proj / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    far = rng.normal(size=(300, 3))
    far *= 3000.0 / np.linalg.norm(far, axis=1, keepdims=True)
    stray = rng.uniform(-30.0, 30.0, (20, 3))
    for p in np.vstack([far, stray]):
        rec.add_point3D(SCALE * rot @ p + shift, pycolmap.Track())
    (rec.write_text if text else rec.write_binary)(str(model))

    orig = Dataset(dataset)
    mm = _distance(orig, "r_000.exr", "r_003.exr")
    out = tmp_path / "data"
    argv = ["dataset", "import", str(proj), "--out", str(out), "--eta-range", "1", "1.5"]
    argv += ["--known-distance", "r_000.exr", "r_003.exr", str(mm)]
    argv += ["--env-rotation", *map(str, info["env_rotation"]), "--up", "keep"]
    assert main(argv) == 0
    done = json.loads(capsys.readouterr().out)
    assert (done["up_from"], done["up_turned_deg"]) == ("--up keep", 0.0)
    assert abs(done["scale"] * SCALE - 1) < 1e-3  # mm per unit: 37
    assert done["split"] == "train/ and test/ names" and done["layout"] == "colmap"
    scene = json.loads((out / "scene.json").read_text())
    assert scene["import"]["scale"] == done["scale"]
    assert scene["import"]["scale_from"] == f"--known-distance r_000.exr r_003.exr {mm} mm"

    new = Dataset(out)
    assert [c.file_path.split("/")[-1] for c in new.test] == [
        f"{c.file_path.split('/')[-1]}.exr" for c in orig.test
    ]
    for a, b in zip(orig.train + orig.test, new.train + new.test):
        # the model's world in mm is R x + shift / s: take the imported camera back by it
        back = rot.T @ (b.position - shift / SCALE)
        assert np.linalg.norm(back - a.position) < 1e-3 * np.linalg.norm(a.position)
        assert (b.width, b.height, b.camera_model) == (a.width, a.height, a.camera_model)
        (_, da), (_, db) = a.rays(), b.rays()
        cos = np.einsum("ni,ni->n", da, db @ rot)
        assert np.arccos(np.clip(cos, -1, 1)).max() < 1e-5  # rad, every pixel's ray
    # the panorama turns with the world: the direction R d sees what d saw
    assert np.allclose(new.scene.envmap_matrix(), rot, atol=1e-9)
    # the box holds the sphere with room for the walls' margin, and not much more
    centre = shift / SCALE
    lo, hi = np.asarray(new.box.lo) - centre, np.asarray(new.box.hi) - centre
    gap = np.concatenate([-RADIUS - lo, hi - RADIUS])
    assert gap.min() > new.box.margin + 4 and gap.max() < 20, gap
    # the far points are not counted (some strays may lie outside the region too)
    used = re.fullmatch(r"the sparse points \((\d+) of 2320 in .*", scene["import"]["box_from"])
    assert used and 2000 <= int(used[1]) <= 2020, scene["import"]["box_from"]


@pytest.mark.parametrize("model", list(READ_MODELS))
def test_each_camera_model_gives_pycolmaps_rays(dataset, tmp_path, model):
    names = READ_MODELS[model][1]
    lens = {"k1": -0.05, "k2": 0.01, "p1": 0.001, "p2": -0.002, "k3": 0.002}
    lens.update(k4=0.001, k5=0.0005, k6=-0.001)
    start = {"f": 40.0, "fx": 40.0, "fy": 43.0, "cx": 15.3, "cy": 17.1}
    params = [start.get(n, lens.get(n)) for n in names]
    proj = _project(tmp_path, dataset, [(model, params)])
    cam = read_colmap(proj, proj / "sparse" / "0").cameras[0]
    (_, d) = cam.rays()
    d_cam = d @ cam.c2w[:3, :3]  # OpenGL camera axes
    j, i = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    xy = pycolmap.Camera(model=model, width=32, height=30, params=params).cam_from_img(
        np.stack([j.ravel(), i.ravel()], axis=1)
    )
    want = np.stack([xy[:, 0], -xy[:, 1], -np.ones(len(xy))], axis=1)
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    cos = np.einsum("ni,ni->n", d_cam, want)
    assert np.arccos(np.clip(cos, -1, 1)).max() < 1e-6  # rad


def _project(tmp, dataset, cameras, images=None, text=False):
    """A small COLMAP project: cameras [(model, params)] of 32 x 30 pixels, images [(name,
    camera_id)] (default three of camera 1, around the origin) as black PNGs, the points of
    a sphere of radius 20, and the dataset's panorama."""
    proj = tmp / "proj"
    model = proj / "sparse" / "0"
    model.mkdir(parents=True)
    rec = pycolmap.Reconstruction()
    for k, (name, params) in enumerate(cameras, start=1):
        add_camera(
            rec, pycolmap.Camera(model=name, width=32, height=30, params=params, camera_id=k)
        )
    images = [("a.png", 1), ("b.png", 1), ("c.png", 1)] if images is None else images
    eyes = [[200.0, 0, 20], [0, 200.0, -20], [-150, -130, 10]]
    for k, ((name, cam_id), eye) in enumerate(zip(images, eyes), start=1):
        image = pycolmap.Image(name=name, camera_id=cam_id, image_id=k)
        add_posed_image(rec, image, pycolmap.Rigid3d(colmap_from_c2w(look_at(eye))))
        (proj / "images").mkdir(exist_ok=True)
        write_png(proj / "images" / name, np.zeros((30, 32, 3)))
    for p in np.random.default_rng(0).normal(size=(100, 3)):
        rec.add_point3D(RADIUS * p / np.linalg.norm(p), pycolmap.Track())
    (rec.write_text if text else rec.write_binary)(str(model))
    shutil.copyfile(dataset / "envmap.exr", proj / "envmap.exr")
    return proj


PINHOLE = ("PINHOLE", [40.0, 40.0, 16.0, 15.0])


def test_bad_projects_are_refused_in_one_line(dataset, tmp_path, capsys):
    def refused(proj, words, *extra):
        out = tmp_path / "out"
        _refused(capsys, ["dataset", "import", str(proj), "--out", str(out), *extra], *words)
        assert not out.exists()  # nothing written
        shutil.rmtree(proj)

    refused(_project(tmp_path, dataset, [PINHOLE], images=[]), ["images.bin", "no registered"])
    opencv = ("OPENCV", [40.0, 40.0, 16.0, 15.0, 0.01, 0, 0, 0])
    proj = _project(tmp_path, dataset, [PINHOLE, opencv], [("a.png", 1), ("b.png", 2)])
    refused(proj, ["cameras.bin", "mixed models (OPENCV, PINHOLE)"])
    fov = ("FOV", [40.0, 40.0, 16.0, 15.0, 0.1])
    refused(_project(tmp_path, dataset, [fov], text=True), ["cameras.txt", "model FOV"])
    proj = _project(tmp_path, dataset, [PINHOLE])
    (proj / "images" / "b.png").unlink()
    refused(proj, [str(proj / "images" / "b.png"), "not found"])
    proj = _project(tmp_path, dataset, [PINHOLE])
    refused(proj, ["images.bin", "'z.png'"], "--known-distance", "a.png", "z.png", "100")


def test_without_pycolmap_says_how_to_install(dataset, tmp_path, capsys, monkeypatch):
    proj = _project(tmp_path, dataset, [PINHOLE])
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # `import pycolmap` fails
    out = tmp_path / "out"
    _refused(capsys, ["dataset", "import", str(proj), "--out", str(out)], "pip install")
    assert not out.exists()


def test_export_then_import_gives_the_same_rays_and_pixels(dataset, tmp_path, capsys):
    proj, out = tmp_path / "proj", tmp_path / "data"
    assert main(["dataset", "export-colmap", str(dataset), "--out", str(proj)]) == 0
    assert json.loads(capsys.readouterr().out)["format"] == "binary"
    assert (proj / "images" / "test" / "r_000.exr").is_file()
    assert main(["dataset", "import", str(proj), "--out", str(out), "--scale", "1"]) == 0
    a, b = Dataset(dataset), Dataset(out)
    for split in ("train", "test"):
        (oa, da, pa), (ob, db, pb) = a.rays_and_pixels(split), b.rays_and_pixels(split)
        assert np.abs(oa - ob).max() < 1e-9 and np.abs(da - db).max() < 1e-12
        assert np.array_equal(pa, pb)
    # again into the same folder: refused, nothing replaced
    _refused(capsys, ["dataset", "export-colmap", str(dataset), "--out", str(proj)], str(proj))


def test_masks_in_colmaps_own_naming_come_with_the_import(dataset, tmp_path, capsys):
    # COLMAP names an image's mask masks/<image name>.png (IMG_1.jpg: masks/IMG_1.jpg.png)
    proj, out = tmp_path / "proj", tmp_path / "data"
    assert main(["dataset", "export-colmap", str(dataset), "--out", str(proj)]) == 0
    masks = {}
    for k, image in enumerate(sorted((proj / "images" / "train").iterdir())[:3]):
        mask = np.zeros((32, 32), np.uint8)
        mask[4 + k : 20, 6:26] = 255  # a different mask per frame
        path = proj / "masks" / "train" / f"{image.name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_png(path, mask)
        masks[image.name] = mask > 127
    assert main(["dataset", "import", str(proj), "--out", str(out), "--scale", "1"]) == 0
    capsys.readouterr()
    ds = Dataset(out)
    found = {Path(c.file_path).name: ds.mask(c) for c in ds.train if ds.has_mask(c)}
    assert found.keys() == masks.keys()
    for name, mask in masks.items():
        assert np.array_equal(found[name], mask), name
    assert not any(ds.has_mask(c) for c in ds.test)


def test_known_distance_also_scales_a_transforms_capture(dataset, tmp_path, capsys):
    orig = Dataset(dataset)
    mm = 3.0 * _distance(orig, "r_001.exr", "r_002.exr")
    out = tmp_path / "data"
    argv = ["dataset", "import", str(dataset), "--out", str(out)]
    assert main([*argv, "--known-distance", "r_001", "r_002.exr", str(mm)]) == 0
    assert abs(json.loads(capsys.readouterr().out)["scale"] / 3.0 - 1) < 1e-9
    _refused(capsys, [*argv, "--known-distance", "r_001", "r_002", "9", "--scale", "2"], "not both")


def _degrees(a: np.ndarray, b: np.ndarray) -> float:
    return float(
        np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))
    )


def _jitter(cams: list[Camera], rng, deg: float) -> list[Camera]:
    """The cameras each turned about its centre by up to about `deg` degrees (a hand's
    wobble), then the whole capture tilted by TILT."""
    out = []
    for c in cams:
        c2w = c.c2w.copy()
        wobble = Rotation.from_rotvec(np.radians(deg) * rng.normal(size=3) / 2).as_matrix()
        c2w[:3, :3] = TILT @ wobble @ c2w[:3, :3]
        c2w[:3, 3] = TILT @ c2w[:3, 3]
        out.append(replace(c, c2w=c2w))
    return out


def _facing(n: int) -> list[Camera]:
    """A forward-facing capture: level cameras on an upright 100 x 40 mm grid, all looking
    at a point 300 mm ahead (their centres lie in a wall, not on the ground)."""
    xs, zs = np.meshgrid(np.linspace(-50, 50, n // 3), [-20.0, 0.0, 20.0])
    cam = fibonacci_sphere_cameras(1, width=32, height=32)[0]
    return [
        replace(cam, c2w=look_at([x, -300.0, z], target=[0.0, 0.0, z]))
        for x, z in zip(xs.ravel(), zs.ravel())
    ]


@pytest.mark.parametrize(
    "layout, source",
    [
        ("orbit", "the plane of the camera centres"),
        ("sphere", "the normal to the cameras' image-right axes"),
        ("facing", "the cameras' mean image-up vector"),
    ],
)
def test_up_is_estimated_from_each_kind_of_capture(layout, source):
    rng = np.random.default_rng(5)
    cams = {
        "orbit": lambda: orbit_cameras(24, elevation_deg=35.0),
        "sphere": lambda: fibonacci_sphere_cameras(16),  # its mean up leans 4.5 degrees
        "facing": lambda: _facing(24),
    }[layout]()
    up, found = estimate_up(_jitter(cams, rng, 0.5), "images.bin")
    assert found == source
    assert _degrees(up, TILT @ Z) < 0.5


def test_cameras_that_disagree_on_up_are_refused():
    # 24 cameras of random roll about their view: their mean image-up vector is short
    rng = np.random.default_rng(2)
    cams = []
    for c in orbit_cameras(24):
        c2w = c.c2w.copy()
        c2w[:3, :3] = (
            c2w[:3, :3] @ Rotation.from_rotvec([0, 0, rng.uniform(0, 2 * np.pi)]).as_matrix()
        )
        cams.append(replace(c, c2w=c2w))
    length = np.linalg.norm(np.mean([c.c2w[:3, 1] for c in cams], axis=0))
    with pytest.raises(ClrefractError, match=r"images\.bin: the cameras disagree .* --up") as e:
        estimate_up(cams, "images.bin")
    assert f"length {length:.2f}" in str(e.value) and length < 0.25


@pytest.fixture(scope="module")
def tilted(dataset, tmp_path_factory):
    """The sphere dataset exported in the similarity (SCALE, TILT, SHIFT), its sparse points
    replaced by a tall ellipsoid about the origin (SEMI_AXES, in the dataset's world):
    (project, export's info, the ellipsoid's points in mm)."""
    proj = tmp_path_factory.mktemp("tilted") / "proj"
    info = export_colmap(dataset, proj, similarity=(SCALE, TILT, SHIFT))
    rec = pycolmap.Reconstruction(str(proj / "sparse" / "0"))
    for pid in list(rec.point3D_ids()):
        rec.delete_point3D(pid)
    p = np.random.default_rng(11).normal(size=(600, 3))
    p = SEMI_AXES * p / np.linalg.norm(p, axis=1, keepdims=True)
    for x in p:
        rec.add_point3D(SCALE * TILT @ x + SHIFT, pycolmap.Track())
    rec.write_binary(str(proj / "sparse" / "0"))
    return proj, info, p


def _turn(orig: Dataset, new: Dataset) -> tuple[np.ndarray, np.ndarray, float]:
    """The rotation M and shift c that take the original cameras' centres onto the imported
    ones (x -> M x + c, least squares), and the largest miss (mm)."""
    a = np.array([c.position for c in orig.train + orig.test])
    b = np.array([c.position for c in new.train + new.test])
    m = Rotation.align_vectors(b - b.mean(0), a - a.mean(0))[0].as_matrix()
    c = b.mean(0) - m @ a.mean(0)
    return m, c, float(np.abs(a @ m.T + c - b).max())


def test_tilted_model_is_levelled(dataset, tilted, tmp_path, capsys):
    proj, info, ellipsoid = tilted
    out = tmp_path / "data"
    argv = ["dataset", "import", str(proj), "--out", str(out), "--scale", str(1 / SCALE)]
    assert main([*argv, "--env-rotation", *map(str, info["env_rotation"])]) == 0
    done = json.loads(capsys.readouterr().out)
    tilt = _degrees(TILT @ Z, Z)
    assert tilt > 60
    assert done["up_from"] == "the normal to the cameras' image-right axes"
    assert abs(done["up_turned_deg"] - tilt) < 0.01
    orig, new = Dataset(dataset), Dataset(out)
    m, c, miss = _turn(orig, new)
    assert miss < 1e-6 * 200  # the centres: the original's, turned and shifted
    assert _degrees(m @ Z, Z) < 1.0  # up is up again: the turn is about z alone
    for a, b in zip(orig.train + orig.test, new.train + new.test):
        assert np.abs(b.c2w[:3, :3] - m @ a.c2w[:3, :3]).max() < 1e-6
    # the panorama turns with the world: about z alone, as the cameras
    assert np.abs(new.scene.envmap_matrix() - m).max() < 1e-6
    # the box is the percentile box of the levelled points, grown alike on every side
    p_lo, p_hi = np.percentile(ellipsoid @ m.T + c, (2, 98), axis=0)
    lo, hi = np.asarray(new.box.lo), np.asarray(new.box.hi)
    assert np.abs((lo + hi) / 2 - (p_lo + p_hi) / 2).max() < 1e-4
    grow = (hi - lo) - (p_hi - p_lo)
    assert np.ptp(grow) < 1e-4 and hi[2] - lo[2] > hi[0] - lo[0] + 30  # tall, as the object
    rec = json.loads((out / "scene.json").read_text())["import"]
    assert rec["up_from"] == done["up_from"] and rec["up_turned_deg"] == done["up_turned_deg"]
    assert _degrees(np.array(rec["up_in_model"]), TILT @ Z) < 1e-6
    assert np.abs(np.array(rec["world_from_model"]) - m @ TILT.T).max() < 1e-6
    assert rec["box_from"].startswith("the sparse points (600 of 600")


def test_explicit_up_is_used(dataset, tilted, tmp_path, capsys):
    proj, _, _ = tilted
    # up 10 degrees off the true one: the import leans by that
    side = np.cross(TILT @ Z, [1.0, 0.0, 0.0])
    off = Rotation.from_rotvec(np.radians(10.0) * side / np.linalg.norm(side)).apply(TILT @ Z)
    out = tmp_path / "data"
    argv = ["dataset", "import", str(proj), "--out", str(out), "--scale", str(1 / SCALE)]
    assert main([*argv, "--up=" + ",".join(f"{x:.12f}" for x in 3.0 * off)]) == 0
    done = json.loads(capsys.readouterr().out)
    assert done["up_from"] == "--up"
    assert abs(done["up_turned_deg"] - _degrees(off, Z)) < 1e-4  # rounded to 4 places
    m, _, miss = _turn(Dataset(dataset), Dataset(out))
    assert miss < 1e-6 * 200 and abs(_degrees(m @ Z, Z) - 10.0) < 1e-6


def test_levelled_import_lets_register_env_find_the_heading(dataset, tilted, tmp_path, capsys):
    proj, _, _ = tilted
    out = tmp_path / "data"
    argv = ["dataset", "import", str(proj), "--out", str(out), "--scale", str(1 / SCALE)]
    assert main(argv) == 0
    capsys.readouterr()
    m, _, _ = _turn(Dataset(dataset), Dataset(out))
    assert abs(np.degrees(np.arctan2(m[1, 0], m[0, 0]))) > 10  # the heading to be found
    found = calibrate(out)["envmap_rotation"]
    assert rotation_angle(found, m) < 1.0  # degrees


@pytest.mark.parametrize("up", ["sideways", "1,2", "0,0,0", "nan,0,1", "1,2,3,4"])
def test_bad_up_is_refused(tilted, tmp_path, capsys, up):
    proj, _, _ = tilted
    out = tmp_path / "data"
    _refused(capsys, ["dataset", "import", str(proj), "--out", str(out), "--up", up], "--up")
    assert not out.exists()


def test_up_on_a_transforms_capture_is_refused(dataset, tmp_path, capsys):
    out = tmp_path / "data"
    argv = ["dataset", "import", str(dataset), "--out", str(out), "--up", "keep"]
    _refused(capsys, argv, "--up is for a COLMAP project")
    assert not out.exists()
