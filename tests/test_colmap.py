"""COLMAP projects: a dataset exported to a COLMAP model in a random similarity imports back to
the same cameras (scale from --known-distance), each COLMAP camera model gives the rays
pycolmap gives, the box comes from the sparse points, and bad input is refused in one line."""

import json
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pycolmap  # the `test` extra installs it
import pytest
from scipy.spatial.transform import Rotation

from clrefract.cameras import look_at
from clrefract.cli import main
from clrefract.colmap import (
    READ_MODELS,
    add_camera,
    add_posed_image,
    colmap_from_c2w,
    export_colmap,
    read_colmap,
)
from clrefract.dataset import Dataset
from clrefract.imageio import write_png
from clrefract.synth import MakeOptions, make_dataset

RADIUS = 20.0  # mm: the sphere scene's object, centred on the origin
SCALE = 1 / 37  # model units per mm of the random similarity


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
    argv += ["--env-rotation", *map(str, info["env_rotation"])]
    assert main(argv) == 0
    done = json.loads(capsys.readouterr().out)
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


def test_known_distance_also_scales_a_transforms_capture(dataset, tmp_path, capsys):
    orig = Dataset(dataset)
    mm = 3.0 * _distance(orig, "r_001.exr", "r_002.exr")
    out = tmp_path / "data"
    argv = ["dataset", "import", str(dataset), "--out", str(out)]
    assert main([*argv, "--known-distance", "r_001", "r_002.exr", str(mm)]) == 0
    assert abs(json.loads(capsys.readouterr().out)["scale"] / 3.0 - 1) < 1e-9
    _refused(capsys, [*argv, "--known-distance", "r_001", "r_002", "9", "--scale", "2"], "not both")
