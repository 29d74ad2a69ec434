"""Every bad input answers in one line that names the problem, with exit status 2, and
leaves what was already in the output folder as it was."""

import hashlib
import json
import os
import shutil
import tempfile

import numpy as np
import pytest

from clrefract.cli import main
from clrefract.imageio import read_exr_rgb, write_exr_rgb
from clrefract.synth import MakeOptions, make_dataset

TINY_FIT = ["--iterations", "2", "--grid-res", "8", "--step", "4", "--test-views", "1"]
TINY_FIT += ["--field-kind", "voxel"]  # these runs were written for a voxel grid


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    out = tmp_path_factory.mktemp("sphere")
    make_dataset("sphere", out, MakeOptions(views=5, res=12, env_width=64, volume_res=12))
    return out


def _copy(ds, tmp_path, name="broken"):
    dst = tmp_path / name
    shutil.copytree(ds, dst)
    return dst


def _snapshot(folder):
    if not folder.exists():
        return {}
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def refused(capsys, args, *needles, keep=None):
    """Run the CLI, expect status 2 and one error line holding every needle; the folder
    `keep` (default: the --out folder, which gets a file of the user's) is left as it was."""
    if keep is None and "--out" in args:
        keep = args[args.index("--out") + 1]
        keep = __import__("pathlib").Path(keep)
        if not keep.exists():
            keep.mkdir(parents=True)
        if keep.is_dir():
            (keep / "notes.txt").write_text("the user's own file")
    before = _snapshot(keep) if keep is not None else None
    code = main([str(a) for a in args])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("clrefract: error:")]
    assert code == 2, err
    assert len(lines) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    if keep is not None:
        assert _snapshot(keep) == before
    return lines[0]


# ---- the tracebacks the issue lists --------------------------------------------------------


def test_fit_out_is_a_file(ds, tmp_path, capsys):
    f = tmp_path / "results.txt"
    f.write_text("precious")
    refused(capsys, ["fit", ds, "--out", f, *TINY_FIT], str(f), "not a folder", keep=tmp_path)
    assert f.read_text() == "precious"


def test_render_res_too_large(tmp_path, capsys):
    refused(capsys, ["render", "--res", 100000, "--out", tmp_path / "r"], "100000x100000", "need")


def test_render_step_too_small(tmp_path, capsys):
    line = refused(capsys, ["render", "--step", 1e-9, "--out", tmp_path / "r"], "step 1e-09 mm")
    assert "at least" in line


def test_render_step_not_positive(tmp_path, capsys):
    refused(capsys, ["render", "--step", "nan", "--out", tmp_path / "r"], "--step")
    refused(capsys, ["render", "--step", "-1", "--out", tmp_path / "r"], "--step")


def test_render_counts(tmp_path, capsys):
    refused(capsys, ["render", "--views", 0, "--out", tmp_path / "r"], "--views")
    refused(capsys, ["render", "--max-steps", -5, "--out", tmp_path / "r"], "--max-steps")
    refused(capsys, ["render", "--radius", 0, "--out", tmp_path / "r"], "--radius")
    refused(capsys, ["render", "--views", 2, "--only", 7, "--out", tmp_path / "r"], "--only")


def test_render_out_is_a_file(tmp_path, capsys):
    f = tmp_path / "renders"
    f.write_text("x")
    refused(capsys, ["render", "--res", 8, "--out", f], "not a folder", keep=tmp_path)


def test_render_missing_inputs(tmp_path, capsys):
    out = tmp_path / "r"
    refused(capsys, ["render", "--cameras", tmp_path / "no.json", "--out", out], "no.json")
    refused(capsys, ["render", "--envmap", tmp_path / "no.exr", "--out", out], "no.exr")
    refused(capsys, ["render", "--field", tmp_path / "f.npz", "--out", out], "f.npz")
    (tmp_path / "g.npz").write_bytes(b"garbage")
    refused(capsys, ["render", "--field", tmp_path / "g.npz", "--out", out], "g.npz")
    refused(capsys, ["render", "--field", "sphere:radius=abc", "--out", out], "abc")


def test_test_renders_keep_one_exr_extension(ds, tmp_path):
    tj = json.loads((ds / "transforms_test.json").read_text())
    for fr in tj["frames"]:
        fr["file_path"] += ".exr"
    (tmp_path / "cams.json").write_text(json.dumps(tj))
    shutil.copytree(ds / "test", tmp_path / "test")
    out = tmp_path / "r"
    args = ["render", "--cameras", tmp_path / "cams.json", "--res", 8, "--out", out]
    assert main([str(a) for a in args + ["--field", "sphere", "--step", "2"]]) == 0
    assert sorted(p.name for p in out.glob("*.exr")) == ["r_000.exr"]


# ---- fits and run folders ------------------------------------------------------------------


def test_fit_refuses_to_overwrite_any_run(ds, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "results.json").write_text("{}")
    refused(capsys, ["fit", ds, "--out", out, *TINY_FIT], "already holds a run")


def test_fit_into_an_unwritable_place(ds, tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    refused(
        capsys,
        ["fit", ds, "--out", tmp_path / "file" / "run", *TINY_FIT],
        "cannot make",
        keep=tmp_path,
    )


def test_fit_into_a_read_only_folder(ds, tmp_path, capsys, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    if os.geteuid() == 0:  # root writes into read-only folders: its probe write is refused

        def refused_write(*args, **kwargs):
            raise PermissionError(13, "Permission denied")

        monkeypatch.setattr(tempfile, "mkstemp", refused_write)
    try:
        refused(capsys, ["fit", ds, "--out", ro, *TINY_FIT], "not writable", keep=ro)
    finally:
        ro.chmod(0o755)


@pytest.fixture(scope="module")
def voxel_run(ds, tmp_path_factory):
    run = tmp_path_factory.mktemp("run") / "voxel"
    assert main([str(a) for a in ["fit", ds, "--out", run, *TINY_FIT, "--init", "empty"]]) == 0
    return run


def test_resume_with_another_field_kind(ds, voxel_run, capsys):
    args = ["fit", ds, "--out", voxel_run, "--resume", "--field", "hashgrid"]
    refused(capsys, args, "--field-kind hashgrid", "voxel")


def test_resume_cannot_lengthen_an_adam_run(ds, voxel_run, capsys):
    args = ["fit", ds, "--out", voxel_run, "--resume", "--iterations", "5"]
    refused(capsys, args, "rates decay over its 2 iterations")


def test_resume_from_a_truncated_checkpoint(ds, voxel_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(voxel_run, run)
    data = (run / "checkpoint.npz").read_bytes()
    (run / "checkpoint.npz").write_bytes(data[: len(data) // 2])
    refused(capsys, ["fit", ds, "--out", run, "--resume"], "checkpoint.npz", "cannot read")


def test_resume_without_a_run(ds, tmp_path, capsys):
    refused(capsys, ["fit", ds, "--out", tmp_path / "new", "--resume"], "no run to resume")


@pytest.mark.parametrize(
    "flags, needle",
    [
        (["--res", "5000"], "res 5000: a 5000^3 grid would need"),
        (["--res", "1"], "res"),
        (["--field", "hashgrid", "--log2-table", "40"], "log2_table"),
        (["--batch", "1000000000"], "batch"),
        (["--iterations", "0"], "iterations"),
        (["--step", "-1"], "step"),
        (["--queues", "0"], "queues"),
    ],
)
def test_fit_sizes_checked_first(ds, tmp_path, capsys, flags, needle):
    refused(capsys, ["fit", ds, "--out", tmp_path / "run", *flags], needle)


def test_fit_config_values(ds, tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text('lr = "fast"\n')
    refused(capsys, ["fit", ds, "--out", tmp_path / "r", "--config", cfg], "'lr'", "fast")
    cfg.write_text("speed = 3\n")
    refused(capsys, ["fit", ds, "--out", tmp_path / "r", "--config", cfg], "speed")
    cfg.write_text("lr = [\n")
    refused(capsys, ["fit", ds, "--out", tmp_path / "r", "--config", cfg], "c.toml", "TOML")
    refused(capsys, ["fit", ds, "--out", tmp_path / "r", "--config", tmp_path / "no.toml"], "no")
    # a key of a fixed set of values, outside it, as the flag would refuse it (refused: the
    # --out folder left as it was)
    from clrefract.fit.config import CHOICES

    for key in CHOICES:
        cfg.write_text(f'{key} = "maybe"\n')
        refused(capsys, ["fit", ds, "--out", tmp_path / "r", "--config", cfg], key, "'maybe'")


# ---- datasets ------------------------------------------------------------------------------


def _fit_refuses(capsys, root, tmp_path, *needles):
    refused(capsys, ["fit", root, "--out", tmp_path / "run", *TINY_FIT], *needles)


def test_dataset_folder_missing(tmp_path, capsys):
    _fit_refuses(capsys, tmp_path / "nowhere", tmp_path, "nowhere", "not found")


def test_frame_corrupt_or_missing(ds, tmp_path, capsys):
    root = _copy(ds, tmp_path)
    (root / "train" / "r_001.exr").write_bytes(b"not an exr")
    _fit_refuses(capsys, root, tmp_path, "r_001.exr")
    (root / "train" / "r_001.exr").unlink()
    (root / "train" / "r_001.png").unlink()
    _fit_refuses(capsys, root, tmp_path, "r_001")


def test_frame_nan_wrong_size_and_no_rgb(ds, tmp_path, capsys):
    import OpenEXR

    root = _copy(ds, tmp_path)
    img = read_exr_rgb(root / "train" / "r_002.exr")
    img[1, 1] = np.nan
    write_exr_rgb(root / "train" / "r_002.exr", img)
    _fit_refuses(capsys, root, tmp_path, "r_002.exr", "NaN")
    write_exr_rgb(root / "train" / "r_002.exr", np.zeros((5, 7, 3), np.float32))
    _fit_refuses(capsys, root, tmp_path, "r_002.exr", "7x5")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": np.zeros((12, 12), np.float32)}) as f:
        f.write(str(root / "train" / "r_002.exr"))
    _fit_refuses(capsys, root, tmp_path, "r_002.exr", "no R, G, B")


def _edit_json(path, fn):
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))


def test_transforms_problems(ds, tmp_path, capsys):
    root = _copy(ds, tmp_path)
    tf = root / "transforms_train.json"
    good = tf.read_text()
    cases = [
        (lambda d: d.update(camera_angle_x="wide"), "camera_angle_x", "finite number"),
        (lambda d: d.update(frames=[]), "'frames' is empty"),
        (lambda d: d["frames"].append(dict(d["frames"][0])), "repeats the image of frames[0]"),
        (lambda d: d["frames"][0].update(transform_matrix=[[1, 0], [0, 1]]), "4x4"),
        (lambda d: d["frames"][1].update(file_path=3), "file_path"),
        (lambda d: d.update(k1=-5.0), "distortion", "folds"),
        (lambda d: d.update(w=12.5), "whole number"),
    ]
    for edit, *needles in cases:
        tf.write_text(good)
        _edit_json(tf, edit)
        _fit_refuses(capsys, root, tmp_path, "transforms_train.json", *needles)
    tf.write_text("{ not json")
    _fit_refuses(capsys, root, tmp_path, "transforms_train.json", "not valid JSON")


def test_scene_file_values(ds, tmp_path, capsys):
    root = _copy(ds, tmp_path)
    _edit_json(root / "scene.json", lambda d: d.update(eta_range=["one", 2]))
    _fit_refuses(capsys, root, tmp_path, "scene.json", "eta_range")
    (root / "scene.json").write_text("[1, 2]")
    _fit_refuses(capsys, root, tmp_path, "scene.json", "JSON object")


def test_cameras_that_do_not_see_the_box(ds, tmp_path, capsys):
    root = _copy(ds, tmp_path)

    def turn_away(d):
        m = np.array(d["frames"][0]["transform_matrix"])
        m[:3, 2] *= -1  # now it looks outward
        m[:3, 0] *= -1
        d["frames"][0]["transform_matrix"] = m.tolist()

    _edit_json(root / "transforms_train.json", turn_away)
    _fit_refuses(capsys, root, tmp_path, "frame 0", "does not see")


def test_environment_map_of_one_pixel(ds, tmp_path, capsys):
    root = _copy(ds, tmp_path)
    write_exr_rgb(root / "envmap.exr", np.ones((1, 1, 3), np.float32))
    _fit_refuses(capsys, root, tmp_path, "envmap.exr", "1x1")
    refused(
        capsys,
        ["render", "--envmap", root / "envmap.exr", "--res", 8, "--out", tmp_path / "r"],
        "1x1",
    )


# ---- meshes and scoring --------------------------------------------------------------------


def _ascii_ply(path, verts, faces):
    lines = [
        "ply",
        "format ascii 1.0",
        f"element vertex {len(verts)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(faces)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    lines += [" ".join(f"{x:.6f}" for x in v) for v in verts]
    lines += ["3 " + " ".join(str(int(i)) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")


def test_meshes_read_in_every_common_format(ds, tmp_path):
    import trimesh

    from clrefract.mesh import read_mesh

    verts, faces = read_mesh(ds / "gt_surface.ply")
    _ascii_ply(tmp_path / "a.ply", verts, faces)
    for name in ("a.obj", "a.stl"):
        trimesh.Trimesh(verts, faces, process=False).export(tmp_path / name)
    for name in ("a.ply", "a.obj", "a.stl"):
        v, f = read_mesh(tmp_path / name)
        # STL stores triangles, not shared vertices: compare the triangles themselves
        assert np.allclose(v[f], verts[faces], atol=1e-4), name


def test_bad_meshes_are_named(tmp_path):
    from clrefract.errors import ClrefractError
    from clrefract.mesh import read_mesh

    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2")
    for path, needle in [
        (tmp_path / "bad.ply", "bad.ply"),
        (tmp_path / "none.ply", "not found"),
        (tmp_path / "a.xyz", "unknown mesh format"),
    ]:
        if path.suffix == ".xyz":
            path.write_text("1 2 3")
        with pytest.raises(ClrefractError, match=needle):
            read_mesh(path)


def test_ascii_ground_truth_is_scored_and_a_bad_one_loses_nothing(ds, tmp_path, capsys):
    from clrefract.dataset import Dataset
    from clrefract.mesh import read_mesh
    from clrefract.report import surface_chamfer
    from clrefract.synth import scene_object

    root = _copy(ds, tmp_path)
    verts, faces = read_mesh(root / "gt_surface.ply")
    _ascii_ply(root / "gt_surface.ply", verts, faces)
    run = tmp_path / "run"
    args = ["fit", root, "--out", run, *TINY_FIT, "--init", "empty"]
    assert main([str(a) for a in args]) == 0
    res = json.loads((run / "results.json").read_text())
    assert "scoring_errors" not in res and "test_psnr" in res
    # the ASCII ground truth scores the true sphere as a close match
    chamfer = surface_chamfer(scene_object("sphere"), Dataset(root))
    assert 0 < chamfer < 0.5, chamfer
    (root / "gt_surface.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n")
    run2 = tmp_path / "run2"
    assert main([str(a) for a in ["fit", root, "--out", run2, *TINY_FIT, "--init", "empty"]]) == 0
    res = json.loads((run2 / "results.json").read_text())
    assert any("gt_surface.ply" in e for e in res["scoring_errors"]), res
    assert res["test_psnr"] is not None and (run2 / "field.npz").is_file()
    assert "warning: scoring failed" in capsys.readouterr().err


# ---- captures ------------------------------------------------------------------------------


def test_import_problems(ds, tmp_path, capsys):
    out = tmp_path / "imported"
    refused(capsys, ["dataset", "import", tmp_path / "nowhere", "--out", out], "not found")
    refused(capsys, ["dataset", "import", tmp_path, "--out", out], "no transforms_train.json")
    refused(capsys, ["dataset", "import", ds, "--out", out, "--scale", "-2"], "--scale")
    refused(capsys, ["dataset", "import", ds, "--out", out, "--eta-range", "2", "1"], "--eta")
    refused(capsys, ["dataset", "import", ds, "--out", ds], "already holds a dataset", keep=ds)


def test_photograph_frames(ds, tmp_path, capsys):
    root = _copy(ds, tmp_path)
    for p in (root / "train").glob("*.exr"):
        p.unlink()  # the PNG previews are now the frames
    _edit_json(root / "scene.json", lambda d: d.update(frames=".png"))
    (root / "train" / "r_002.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    _fit_refuses(capsys, root, tmp_path, "r_002.png", "not a readable")
    _edit_json(root / "scene.json", lambda d: d.update(frames=".tiff"))
    _fit_refuses(capsys, root, tmp_path, "scene.json", "'frames'")
    _edit_json(root / "scene.json", lambda d: d.update(frames=".png", units="inch"))
    _fit_refuses(capsys, root, tmp_path, "scene.json", "units")


def test_bad_exposure_and_mask(ds, tmp_path, capsys):
    root = _copy(ds, tmp_path)
    tf = root / "transforms_train.json"
    good = tf.read_text()
    _edit_json(tf, lambda d: d["frames"][0].update(exposure_scale=0))
    _fit_refuses(capsys, root, tmp_path, "exposure_scale", "positive")
    tf.write_text(good)
    _edit_json(tf, lambda d: d["frames"][0].update(mask_path="masks/none.png"))
    _fit_refuses(capsys, root, tmp_path, "none.png", "mask file not found")


# ---- --box, the start, surfaces -----------------------------------------------------------


@pytest.mark.parametrize(
    "box, needle",
    [
        ("1,2,3,4,5", "six numbers"),
        ("-30,-30,-30,30,30,30,30", "got 7"),
        ("-30,a,-30,30,30,30", "'a' is not a number"),
        ("-30,-30,-30,30,nan,30", "finite"),
        ("-30,-30,30,30,30,30", "zmin must be below zmax, got 30 >= 30"),
        ("30,-30,-30,-30,30,30", "xmin must be below xmax"),
    ],
)
def test_bad_box_strings(ds, tmp_path, capsys, box, needle):
    refused(capsys, ["fit", ds, "--out", tmp_path / "run", "--box", box, *TINY_FIT], needle)
    refused(capsys, ["dataset", "check", ds, "--box", box], "--box", needle)
    out = tmp_path / "imported"
    refused(capsys, ["dataset", "import", ds, "--out", out, "--box", box], needle)


def _empty_masks(root):
    """User masks that mark nothing: the visual hull of a level-set start is then empty."""
    import imageio.v3 as iio

    (root / "masks").mkdir()
    for tf in ("transforms_train.json", "transforms_test.json"):
        for fr in json.loads((root / tf).read_text())["frames"]:
            stem = fr["file_path"].split("/")[-1]
            iio.imwrite(root / "masks" / f"{stem}.png", np.zeros((12, 12), np.uint8))


def test_a_failed_start_leaves_no_run_behind(ds, tmp_path, capsys):
    root = _copy(ds, tmp_path)
    _empty_masks(root)
    args = ["fit", root, "--out", tmp_path / "run", *TINY_FIT, "--field", "levelset"]
    # the folder held the user's file only: it holds just that again (refused() compares)
    refused(capsys, args, "refraction masks do not agree")
    fresh = tmp_path / "fresh" / "run"
    code = main([str(a) for a in ["fit", root, "--out", fresh, *TINY_FIT, "--field", "levelset"]])
    assert code == 2 and not fresh.exists(), list(fresh.iterdir()) if fresh.exists() else None
    assert (tmp_path / "fresh").is_dir()  # a folder made by ensure_out_dir's parents: kept


def test_fit_box_overrides_the_scene_and_the_surface_is_written(ds, tmp_path, monkeypatch):
    """--box replaces scene.json's box (the run records it, eval uses it); the surface that
    the chamfer distance scores is written as surface.ply, the same by fit and eval."""
    from clrefract.evaluate import evaluate_run
    from clrefract.fields import load_field_file
    from clrefract.fit import load_config
    from clrefract.mesh import read_mesh
    from clrefract.metrics import eta_surface

    root = _copy(ds, tmp_path)
    (root / "gt_surface.ply").unlink()  # no chamfer: it is slow on surfaces this far apart
    run = tmp_path / "run"
    box = "-40,-38,-36,36,38,40"
    assert main([str(a) for a in ["fit", root, "--out", run, "--box", box, *TINY_FIT]]) == 0
    meta = json.loads((run / "run.json").read_text())
    assert meta["box"]["lo"] == [-40, -38, -36] and meta["box"]["hi"] == [36, 38, 40]
    assert load_config(run / "config.toml", {}).box == (-40, -38, -36, 36, 38, 40)
    res = json.loads((run / "results.json").read_text())
    assert res["surface"] == "surface.ply" and "scoring_errors" not in res, res
    verts, faces = read_mesh(run / "surface.ply")
    assert len(faces) > 100
    assert np.all(verts >= [-40, -38, -36]) and np.all(verts <= [36, 38, 40])
    # the mesh is marching cubes of the fitted eta halfway to the scene's index, in the box
    # (the fit's eta is the device's float32, this the NumPy float64: a sample within
    # rounding of the level may order the vertices otherwise, so they are compared as sets)
    from scipy.spatial import cKDTree

    from clrefract.dataset import Dataset
    from clrefract.fields.base import Box
    from clrefract.report import surface_level

    def same_vertices(a, b) -> bool:
        return len(a) == len(b) and cKDTree(a).query(b)[0].max() < 1e-3

    field = load_field_file(run / "field.npz", Box.from_dict(meta["box"]))
    want = eta_surface(field, field.box, surface_level(Dataset(root)))
    assert len(want[1]) == len(faces) and same_vertices(want[0], verts)
    ev = evaluate_run(run, figures=False, views=1)
    assert ev["surface"] == "surface.ply"
    got = read_mesh(run / "eval" / "surface.ply")
    assert len(got[1]) == len(faces) and same_vertices(got[0], verts)
    # an extraction that fails is named in scoring_errors; the run keeps everything else
    import clrefract.metrics

    def broken(*a, **k):
        raise RuntimeError("marching cubes fell over")

    monkeypatch.setattr(clrefract.metrics, "eta_surface", broken)
    run2 = tmp_path / "run2"
    assert main([str(a) for a in ["fit", root, "--out", run2, *TINY_FIT, "--init", "empty"]]) == 0
    res2 = json.loads((run2 / "results.json").read_text())
    assert "surface: marching cubes fell over" in res2["scoring_errors"], res2
    assert res2["test_psnr"] is not None and (run2 / "field.npz").is_file()
    assert not (run2 / "surface.ply").exists()
