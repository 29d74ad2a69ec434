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
from clrefract.importer import NGP_KEYS
from clrefract.synth import MakeOptions, make_dataset

UNIT_MM = 100.0  # the capture's poses are in decimetres, as Blender scenes are about 4 units


def _to_capture(ds, cap, ngp=False):
    """A rendered dataset rewritten the way a NeRF-synthetic (Blender) capture comes: RGBA
    8-bit PNG frames named without extension, poses in decimetres, only camera_angle_x, no
    scene.json; with ngp, one transforms.json with instant-ngp's aabb_scale, scale and offset
    instead (its box: -105..95, -100..100, -95..105 mm)."""
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
        top = {"camera_angle_x": tj["camera_angle_x"], "frames": frames_all}
        top.update(aabb_scale=4, scale=2.0, offset=[0.6, 0.5, 0.4])
        (cap / "transforms.json").write_text(json.dumps(top))
    else:
        shutil.copy(cap / "transforms_test.json", cap / "transforms_val.json")
    shutil.copy(ds / "envmap.exr", cap / "envmap.exr")
    return cap


def _srgb(x):
    """IEC 61966-2-1 encoding of linear values clipped to [0, 1], in float64."""
    x = np.clip(np.asarray(x, np.float64), 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


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
    out = capsys.readouterr().out
    assert "millimetres" not in out
    # 8 + 2 views, distance / focal length in pixels, median: the grid --res 0 would pick
    d0, centre = Dataset(ds), (lo + hi) / 2
    foot = np.median([np.linalg.norm(c.position - centre) / c.fl_x for c in (*d0.train, *d0.test)])
    assert f"one pixel spans {foot:.2f} mm at the box centre" in out, out
    # the photographs read back as the linear renders, to 8-bit precision
    d = Dataset(ds)
    img = d.image(d.train[0])
    ref = read_exr_rgb(rendered / "train" / "r_001.exr")
    assert np.allclose(linear_to_srgb(img), linear_to_srgb(ref), atol=1 / 255 + 1e-6)
    run = tmp_path / "run"
    args = ["fit", ds, "--out", run, "--iterations", "3", "--res", "8", "--step", "4"]
    assert main([str(a) for a in args + ["--test-views", "1"]]) == 0
    res = json.loads((run / "results.json").read_text())
    assert res["iterations"] == 3 and len(res["views"]) == 1
    # the score against the float64 formula on the test view the fit rendered and saved
    # (measured off by 4e-7 dB: float32 sRGB), and above the score of the environment alone
    # (no object) there: measured 24.75 against 24.57 dB
    cam, view = d.test[0], res["views"][0]
    ref = _srgb(d.image(cam))
    got = _srgb(read_exr_rgb(run / "test" / f"{view['view']}.exr"))
    bare = _srgb(d.envmap().lookup(cam.rays()[1]).reshape(ref.shape))
    psnr, bare_psnr = (-10 * np.log10(np.mean((x - ref) ** 2)) for x in (got, bare))
    assert view["psnr"] == pytest.approx(psnr, abs=4e-6) and res["test_psnr"] == view["psnr"]
    assert res["test_psnr"] > bare_psnr + 0.05, (res["test_psnr"], bare_psnr)
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
    got = fit.rays.masks()
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


def test_instant_ngp_box_keys_are_honoured(rendered, tmp_path, capsys):
    """instant-ngp maps p to p * scale + offset and traces the cube of side aabb_scale about
    (0.5, 0.5, 0.5): the fixture's keys give -105..95, -100..100, -95..105 mm."""
    cap = _to_capture(rendered, tmp_path / "ngp", ngp=True)
    ds = tmp_path / "ds"
    assert main(["dataset", "import", str(cap), "--out", str(ds), "--scale", str(UNIT_MM)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["box_from"] == "instant-ngp aabb_scale 4"
    assert np.allclose(info["box"]["lo"], [-105, -100, -95])
    assert np.allclose(info["box"]["hi"], [95, 100, 105])
    assert main(["dataset", "check", str(ds)]) == 0
    assert "OK" in capsys.readouterr().out
    # aabb_scale 16 takes in the cameras (instant-ngp's background): the unit cube instead
    tf = cap / "transforms.json"
    tj = json.loads(tf.read_text())
    tf.write_text(json.dumps({**tj, "aabb_scale": 16}))
    assert main(["dataset", "import", str(cap), "--out", str(tmp_path / "d16")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["box_from"] == "instant-ngp aabb_scale 1"
    assert np.allclose(info["box"]["lo"], [-0.3, -0.25, -0.2])  # no --scale: poses' units
    assert np.allclose(info["box"]["hi"], [0.2, 0.25, 0.3])
    # --pose-box wins, given as one comma-separated string, in the poses' units
    args = [
        "--out",
        str(tmp_path / "dbox"),
        "--scale",
        "100",
        "--pose-box",
        "-0.3,-0.3,-0.3,0.3,0.3,0.3",
    ]
    assert main(["dataset", "import", str(cap), *args]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["box_from"] == "--pose-box" and np.allclose(info["box"]["hi"], [30, 30, 30])
    # a bad key, and a cube that holds cameras even at aabb_scale 1, are refused
    tf.write_text(json.dumps({**tj, "scale": -1}))
    assert main(["dataset", "import", str(cap), "--out", str(tmp_path / "bad")]) == 2
    assert "'scale' and 'aabb_scale' must be positive" in capsys.readouterr().err
    tf.write_text(json.dumps({**tj, "scale": 0.1}))
    assert main(["dataset", "import", str(cap), "--out", str(tmp_path / "bad")]) == 2
    assert "holds cameras; give the object's box with --pose-box" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    # without any of the keys: the region the cameras look at, as before
    tf.write_text(json.dumps({k: v for k, v in tj.items() if k not in NGP_KEYS}))
    assert main(["dataset", "import", str(cap), "--out", str(tmp_path / "dcam")]) == 0
    assert json.loads(capsys.readouterr().out)["box_from"] == "the cameras"


def _cut_out(png, keep_background: bool):
    """An RGBA frame whose alpha marks the object (the middle 8 x 8), its background
    either kept (a matte) or cut away to black (NeRF-synthetic's transparent film)."""
    img = iio.imread(png)
    alpha = np.zeros(img.shape[:2], np.uint8)
    alpha[4:12, 4:12] = 255
    if not keep_background:
        img[alpha == 0, :3] = 0
    img[..., 3] = alpha
    iio.imwrite(png, img)
    return alpha > 127


def test_alpha_is_the_mask_and_a_cut_away_background_is_refused(rendered, tmp_path, capsys):
    from clrefract.fit import Fit, load_config

    cap = _to_capture(rendered, tmp_path / "capture")
    matte = _cut_out(cap / "train" / "r_001.png", keep_background=True)
    d = Dataset(cap)
    first, second = d.train[0], d.train[1]
    assert d.has_mask(first) and np.array_equal(d.mask(first), matte)
    assert not d.has_mask(second)  # opaque everywhere: no mask
    rgb, _ = read_photo_rgb(cap / "train" / "r_001.png")
    assert np.array_equal(d.image(first), rgb)  # RGB as stored, not premultiplied
    fit = Fit(cap, tmp_path / "run", load_config(None, {"res": 8}))
    assert np.array_equal(fit.rays.masks()[0], matte)
    assert main(["dataset", "check", str(cap)]) == 0
    capsys.readouterr()
    # the background cut away: no environment to compare with, refused in one line
    _cut_out(cap / "train" / "r_002.png", keep_background=False)
    with pytest.raises(ClrefractError, match=r"r_002.png: transparent background \(75%"):
        Dataset(cap).image(Dataset(cap).train[1])
    assert main(["dataset", "check", str(cap)]) == 2
    assert "r_002.png: transparent background" in capsys.readouterr().out
    args = [
        "fit",
        str(cap),
        "--out",
        str(tmp_path / "run2"),
        "--iterations",
        "1",
        "--grid-res",
        "8",
        "--field-kind",
        "voxel",
    ]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "transparent background" in err


def test_masks_folder_is_checked_and_nameless_frames_have_their_own(rendered, tmp_path, capsys):
    cap = _to_capture(rendered, tmp_path / "capture")
    (cap / "masks").mkdir()
    iio.imwrite(cap / "masks" / "r_002.png", np.zeros((5, 5), np.uint8))
    assert main(["dataset", "check", str(cap)]) == 2
    assert "masks/r_002.png: mask is 5x5 but its camera says 16x16" in capsys.readouterr().out
    (cap / "masks" / "r_002.png").unlink()
    iio.imwrite(cap / "masks" / "r_001.png", np.full((16, 16), 255, np.uint8))
    out = tmp_path / "ds"  # the import takes masks/<frame> along
    assert main(["dataset", "import", str(cap), "--out", str(out), "--scale", "100"]) == 0
    imported = Dataset(out)
    assert imported.mask(imported.train[0]).all() and not imported.has_mask(imported.train[1])
    d = Dataset(cap)
    for k, cam in enumerate(d.train[:3]):  # frames made without a file or a name
        cam.file_path = cam.name = ""
        m = np.zeros((16, 16), np.uint8)
        m[k] = 255
        iio.imwrite(cap / "masks" / f"view_{k:03d}.png", m)
    got = [d.mask(cam) for cam in d.train[:3]]
    assert [d.mask_path(c).name for c in d.train[:3]] == [f"view_00{k}.png" for k in range(3)]
    assert [int(np.flatnonzero(g.any(1))[0]) for g in got] == [0, 1, 2]
