"""Your own capture: photographs as PNG or JPEG, no scene.json, NeRF-synthetic and
instant-ngp layouts imported, checked and fitted with no hand-written file."""

import json
import shutil

import imageio.v3 as iio
import numpy as np
import pytest

from clrefract.cli import main
from clrefract.dataset import Dataset, read_scene
from clrefract.errors import ClrefractError
from clrefract.imageio import linear_to_srgb, read_exr_rgb, read_photo_rgb
from clrefract.synth import MakeOptions, make_dataset

UNIT_MM = 100.0  # the capture's poses are in decimetres, as Blender scenes are about 4 units


def _to_capture(ds, cap, ngp=False):
    """A rendered dataset rewritten the way a NeRF-synthetic (Blender) capture comes: RGBA
    8-bit PNG frames named without extension, poses in decimetres, only camera_angle_x, no
    scene.json; with ngp, one transforms.json with aabb_scale instead."""
    cap.mkdir()
    frames_all = []
    for split in ("train", "test"):
        tj = json.loads((ds / f"transforms_{split}.json").read_text())
        (cap / split).mkdir()
        for fr in tj["frames"]:
            m = np.array(fr["transform_matrix"])
            m[:3, 3] /= UNIT_MM
            fr["transform_matrix"] = m.tolist()
            name = fr["file_path"].split("/")[-1]
            img = read_exr_rgb(ds / split / f"{name}.exr")
            rgba = np.concatenate([linear_to_srgb(img), np.ones_like(img[..., :1])], axis=-1)
            iio.imwrite(cap / split / f"{name}.png", np.round(rgba * 255).astype(np.uint8))
            for key in ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_angle_x"):
                fr.pop(key, None)
        top = {"camera_angle_x": tj["camera_angle_x"], "frames": tj["frames"]}
        frames_all += tj["frames"]
        if not ngp:
            (cap / f"transforms_{split}.json").write_text(json.dumps(top))
    if ngp:
        top = {"camera_angle_x": tj["camera_angle_x"], "aabb_scale": 4, "frames": frames_all}
        (cap / "transforms.json").write_text(json.dumps(top))
    else:
        shutil.copy(cap / "transforms_test.json", cap / "transforms_val.json")
    shutil.copy(ds / "envmap.exr", cap / "envmap.exr")
    return cap


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    out = tmp_path_factory.mktemp("sphere")
    make_dataset("sphere", out, MakeOptions(views=10, res=16, env_width=128, volume_res=12))
    return out


def test_nerf_synthetic_capture_imports_checks_and_fits(rendered, tmp_path, capsys):
    cap = _to_capture(rendered, tmp_path / "capture")
    assert not (cap / "scene.json").exists()
    # the capture as it is: readable, with what was assumed said, and a doubt about units
    assert main(["dataset", "check", str(cap)]) == 0
    said = capsys.readouterr().out
    assert "assumed no scene.json" in said and "box from the cameras" in said
    assert "millimetres" in said
    ds = tmp_path / "ds"
    assert main(["dataset", "import", str(cap), "--out", str(ds), "--scale", str(UNIT_MM)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["layout"] == "nerf-synthetic" and info["frames"] == ".png"
    assert (info["train"], info["test"]) == (8, 2)
    # the box the cameras look at holds the 20 mm sphere at the origin
    lo, hi = np.array(info["box"]["lo"]), np.array(info["box"]["hi"])
    assert np.all(lo < -20) and np.all(hi > 20) and np.all(np.abs(lo + hi) < 1)
    assert main(["dataset", "check", str(ds)]) == 0
    assert "millimetres" not in capsys.readouterr().out
    # the photographs read back as the linear renders, to 8-bit precision
    d = Dataset(ds)
    img = d.image(d.train[0])
    ref = read_exr_rgb(rendered / "train" / "r_001.exr")
    assert np.allclose(linear_to_srgb(img), linear_to_srgb(ref), atol=1 / 255 + 1e-6)
    run = tmp_path / "run"
    args = ["fit", ds, "--out", run, "--iterations", "3", "--res", "8", "--step", "4"]
    assert main([str(a) for a in args + ["--test-views", "1"]]) == 0
    res = json.loads((run / "results.json").read_text())
    assert res["iterations"] == 3 and res["test_psnr"] > 10
    assert "scoring_errors" not in res


def test_instant_ngp_capture_holds_out_every_eighth_frame(rendered, tmp_path, capsys):
    cap = _to_capture(rendered, tmp_path / "ngp", ngp=True)
    ds = tmp_path / "ds"
    assert main(["dataset", "import", str(cap), "--out", str(ds), "--scale", str(UNIT_MM)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["layout"] == "instant-ngp" and info["test"] == 2 and info["train"] == 8
    # importing again would replace the dataset: refused, nothing touched
    before = (ds / "scene.json").read_bytes()
    assert main(["dataset", "import", str(cap), "--out", str(ds)]) == 2
    assert "already holds a dataset" in capsys.readouterr().err
    assert (ds / "scene.json").read_bytes() == before
    # and used in place, without scene.json: the same split
    d = Dataset(cap)
    assert read_scene(cap).test == "transforms.json"
    assert [c.name for c in d.test] == [c.name for c in Dataset(ds).test]
    assert len(d.train) == 8 and not {c.name for c in d.train} & {c.name for c in d.test}


def test_import_needs_an_environment_map(rendered, tmp_path, capsys):
    cap = _to_capture(rendered, tmp_path / "capture")
    (cap / "envmap.exr").unlink()
    assert main(["dataset", "import", str(cap), "--out", str(tmp_path / "ds")]) == 2
    assert "--envmap" in capsys.readouterr().err
    assert not (tmp_path / "ds").exists()


def test_photographs_decode_srgb_and_mark_clipped_pixels(tmp_path):
    enc = np.array([[[0, 128, 255], [10, 20, 30]], [[254, 0, 0], [253, 253, 253]]], np.uint8)
    iio.imwrite(tmp_path / "a.png", enc)
    lin, clipped = read_photo_rgb(tmp_path / "a.png")
    assert np.allclose(linear_to_srgb(lin) * 255, enc, atol=0.01)
    assert clipped.tolist() == [[True, False], [True, False]]
    iio.imwrite(tmp_path / "g.png", enc[..., 0])  # grey
    lin_g, _ = read_photo_rgb(tmp_path / "g.png")
    assert lin_g.shape == (2, 2, 3) and np.allclose(lin_g[..., 0], lin_g[..., 2])
    iio.imwrite(tmp_path / "a.jpg", np.full((8, 8, 3), 128, np.uint8))
    lin_j, _ = read_photo_rgb(tmp_path / "a.jpg")
    assert abs(float(lin_j.mean()) - 0.2158) < 0.01  # sRGB 128 is 21.6 % linear
    (tmp_path / "bad.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(ClrefractError, match="bad.png: not a readable"):
        read_photo_rgb(tmp_path / "bad.png")


def test_clipped_pixels_weigh_nothing_and_exposure_scales(rendered, tmp_path, capsys):
    cap = _to_capture(rendered, tmp_path / "capture")
    tf = cap / "transforms_train.json"
    tj = json.loads(tf.read_text())
    tj["frames"][0]["exposure_scale"] = 2.0
    tf.write_text(json.dumps(tj))
    png = cap / "train" / "r_001.png"
    img = iio.imread(png)
    img[0, :4, 0] = 255  # the first four pixels clipped in red
    iio.imwrite(png, img)
    d = Dataset(cap)
    _, _, rgb = d.rays_and_pixels("train")
    w = d.pixel_weights("train")
    n = d.train[0].width * d.train[0].height
    clipped = (img[..., :3] >= 254).any(-1).ravel()
    assert w[:4].tolist() == [0, 0, 0, 0] and clipped.sum() >= 4
    assert np.array_equal(w[:n] == 0, clipped)
    plain, _ = read_photo_rgb(png)
    assert np.allclose(rgb[:n].reshape(plain.shape), 2.0 * plain)
    assert np.allclose(
        rgb[n : 2 * n], read_photo_rgb(cap / "train" / "r_002.png")[0].reshape(-1, 3)
    )


def test_scene_keys_named_in_plain_words(rendered, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(rendered, root)
    scene = json.loads((root / "scene.json").read_text())
    scene["box"] = {"lo": [-50, -50, -50], "hi": [50, 50, 50]}  # no margin: the default
    (root / "scene.json").write_text(json.dumps(scene))
    s = read_scene(root)
    assert s.box.margin == 4.0 and any("margin" in a for a in s.assumed)
    scene["box"] = {"hi": [50, 50, 50]}
    (root / "scene.json").write_text(json.dumps(scene))
    with pytest.raises(ClrefractError, match="'box' needs 'lo', its lowest corner"):
        read_scene(root)
    scene["box"] = {"lo": [-50, "x", -50], "hi": [50, 50, 50]}
    (root / "scene.json").write_text(json.dumps(scene))
    with pytest.raises(ClrefractError, match="box 'lo' must be 3 numbers"):
        read_scene(root)
    scene["units"] = "m"
    (root / "scene.json").write_text(json.dumps(scene))
    with pytest.raises(ClrefractError, match="units must be"):
        read_scene(root)


def test_user_masks_feed_the_start(rendered, tmp_path):
    from clrefract.fit import Fit, load_config

    cap = _to_capture(rendered, tmp_path / "capture")
    (cap / "masks").mkdir()
    d = Dataset(cap)
    masks = []
    for k, cam in enumerate(d.train):
        m = np.zeros((cam.height, cam.width), np.uint8)
        m[k % cam.height, :] = 255  # a different stripe per frame
        iio.imwrite(cap / "masks" / f"{cam.name.removesuffix('.png')}.png", m)
        masks.append(m > 0)
    tj = json.loads((cap / "transforms_train.json").read_text())
    tj["frames"][1]["mask_path"] = "masks/other.png"  # a per-frame path beats the folder
    other = np.zeros((16, 16, 4), np.uint8)
    other[:2, :2, 3] = 255  # a cut-out: the alpha channel is the mask
    iio.imwrite(cap / "masks" / "other.png", other)
    masks[1] = other[..., 3] > 0
    (cap / "transforms_train.json").write_text(json.dumps(tj))
    fit = Fit(cap, tmp_path / "run", load_config(None, {"res": 8}))
    got = fit._refraction_masks()
    assert all(np.array_equal(g, m) for g, m in zip(got, masks))
    iio.imwrite(cap / "masks" / "other.png", np.zeros((5, 5), np.uint8))
    with pytest.raises(ClrefractError, match="other.png: mask is 5x5"):
        Dataset(cap).mask(Dataset(cap).train[1])


def test_import_without_test_file_holds_out_and_keeps_mask_names(rendered, tmp_path, capsys):
    """A NeRF-synthetic capture with no transforms_test.json: every 8th frame becomes a test
    view and leaves the training set; a mask named without extension loads after import."""
    cap = _to_capture(rendered, tmp_path / "capture")
    (cap / "transforms_test.json").unlink()
    (cap / "masks").mkdir()
    tj = json.loads((cap / "transforms_train.json").read_text())
    tj["frames"][1]["mask_path"] = "masks/m1"
    iio.imwrite(cap / "masks" / "m1.png", np.full((16, 16), 255, np.uint8))
    (cap / "transforms_train.json").write_text(json.dumps(tj))
    ds = tmp_path / "ds"
    assert main(["dataset", "import", str(cap), "--out", str(ds), "--scale", str(UNIT_MM)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["train"], info["test"]) == (7, 1)
    d = Dataset(ds)
    assert not {c.name for c in d.train} & {c.name for c in d.test}
    assert d.mask(d.train[0]).all()  # frame 1 is the first training frame left
