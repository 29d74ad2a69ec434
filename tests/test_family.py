"""Family shapes (issue 15): their SDFs against known distances, the SDF Snell renderer against
the analytic sphere renderer and against an independent dense-sampling reference, meshes on the
zero set, seeds, input errors, and a family dataset end to end."""

import json

import numpy as np
import pytest
from rays import camera_rays, unit

from clrefract.cameras import fibonacci_sphere_cameras
from clrefract.cli import main
from clrefract.dataset import Dataset, check_dataset
from clrefract.envmap import EnvMap
from clrefract.errors import ClrefractError
from clrefract.family import (
    FAMILY,
    LIMIT,
    Bowl,
    RandomSolid,
    SdfSphere,
    TwoBodies,
    Vase,
    make_shape,
    shape_from_dict,
)
from clrefract.fields.analytic import Sphere
from clrefract.fields.voxel import VoxelGrid
from clrefract.mesh import read_mesh
from clrefract.report import scene_truth
from clrefract.snell import SnellRenderer
from clrefract.snell_sdf import SdfSnellRenderer, snell_sdf_numpy
from clrefract.synth import MakeOptions, make_dataset
from clrefract.tracer import Status


def _world(shape, local):
    """Local points (n, 3) of a shape to world: x = c + M^T l."""
    return np.asarray(local, float) @ shape.world_to_local + np.asarray(shape.center)


# -------------------------------------------------------------- the renderer on a ball


def test_sdf_renderer_matches_the_analytic_sphere():
    c = (3.0, -2.0, 1.0)
    ball = SdfSphere(radius=20.0, eta=1.5, center=c, tilt=(10.0, 20.0, 30.0))
    exact = SnellRenderer(Sphere(radius=20.0, eta=1.5, center=c))
    sdf = SdfSnellRenderer(ball, precision="float64")
    o, d = camera_rays(3000, 25.0, c, seed=1)
    a, b = exact.trace(o, d), sdf.trace(o, d)
    assert np.array_equal(a.status, b.status) and np.array_equal(a.events, b.events)
    assert (b.status == Status.EXITED).sum() > 1000 and (b.status == Status.MISSED).sum() > 500
    assert np.abs(a.direction - b.direction).max() < 1e-6
    hit = b.status == Status.EXITED
    assert np.abs(a.surface[hit] - b.surface[hit]).max() < 1e-6
    # camera images through the environment map
    env = EnvMap.procedural(256, 128, seed=3)
    for cam in fibonacci_sphere_cameras(2, width=32, height=32):
        o, d = cam.rays()
        ia = env.lookup(exact.trace(o, d).direction)
        ib = env.lookup(sdf.trace(o, d).direction)
        assert np.abs(ia - ib).max() < 1e-4


# ------------------------------------------------------------------ every family shape


def _known_distances(shape):
    """(local point, exact signed distance) pairs from each shape's geometry."""
    if shape.kind == "rounded-cube":  # size 30: faces at 15
        return [((15.5, 0, 0), 0.5), ((0, 14.0, 0), -1.0), ((0, 0, 0), -15.0)]
    if shape.kind == "cylinder":  # radius 14, height 32
        return [((14.5, 0, 0), 0.5), ((0, 0, 17.0), 1.0), ((0, 0, 0), -14.0)]
    if shape.kind == "bowl":  # mid-wall 18, wall 5, cut at z = 8
        w = np.sqrt(18.0**2 - 8.0**2)
        return [
            ((0, 0, -18.0), -2.5),
            ((0, 0, 0), 15.5),  # the hollow is outside the glass
            ((0, 0, -21.0), 0.5),
            ((w, 0, 9.0), -1.5),  # 1 mm above the rim circle, in its rounded lip
            ((0, 0, 18.0), np.hypot(w, 10.0) - 2.5),  # over the opening: nearest is the rim
        ]
    if shape.kind == "two-bodies":
        xs, xb = shape._centres()
        gap_mid = xs + shape.sphere_radius + 0.5 * shape.gap
        return [((xs, 0, 0), -10.0), ((xb, 0, 0), -8.0), ((gap_mid, 0, 0), 3.0)]
    if shape.kind == "vase":  # waist 7.5 at z = -4, flat ends at +-20
        return [((8.0, 0, -4.0), 0.5), ((0, 0, 20.5), 0.5), ((0, 0, 0), None)]
    if shape.kind == "random":  # the first capsule passes through the origin
        return [((0, 0, 0), None)]
    if shape.kind == "faceted":  # inside, the distance to the nearest face's plane
        f = np.asarray(shape.faces)
        return [((0, 0, 0), -float(f[:, 3].min())), ((0, 0, 0), None)]
    raise AssertionError(shape.kind)


@pytest.mark.parametrize("name", FAMILY)
def test_family_shape_sdf_renders_and_meshes(name):
    shape = make_shape(name)
    # signs and exact distances at known points, in the tilted world frame
    for loc, want in _known_distances(shape):
        got = float(shape.distance(_world(shape, [loc]))[0])
        if want is None:
            assert got < -3.0, (loc, got)
        else:
            assert got == pytest.approx(want, abs=1e-9), (loc, got)
    # outside the bounding sphere everything is outside, and the bound is within the limit
    rng = np.random.default_rng(0)
    far = np.asarray(shape.center) + (shape.bounding_radius + 0.5) * unit(rng.normal(size=(500, 3)))
    assert np.all(shape.distance(far) > 0) and not shape.inside(far).any()
    assert 10.0 <= shape.bounding_radius <= LIMIT
    # the kernel on a small camera set: finite, nearly all rays leave
    r = SdfSnellRenderer(shape)
    hits = trapped = 0
    for cam in fibonacci_sphere_cameras(4, width=24, height=24):
        o, d = cam.rays()
        res = r.trace(o, d)
        assert np.all(np.isfinite(res.direction)) and np.all(np.isfinite(res.position))
        assert not np.any(res.status == Status.NONFINITE)
        hit = res.status != Status.MISSED
        hits += int(hit.sum())
        trapped += int((res.status == Status.TRAPPED).sum())
        # every hit ray's last event lies on the surface
        assert np.abs(shape.distance(res.surface[hit])).max() < 1e-8
        # refraction turns or shifts every ray that went through (parallel cube faces only
        # shift it)
        turned = np.linalg.norm(res.direction - unit(d), axis=1) > 1e-3
        shifted = np.linalg.norm(np.cross(res.surface - o, unit(d)), axis=1) > 1e-3
        assert (turned | shifted)[res.status == Status.EXITED].mean() > 0.95
    assert hits > 80 and trapped <= 0.02 * hits
    # mesh: non-empty, on the zero set, as big as the object
    verts, faces = shape.mesh(spacing=0.8)
    assert len(faces) > 1000
    assert np.abs(shape.distance(verts)).max() < 1e-6
    rad = np.linalg.norm(verts - np.asarray(shape.center), axis=1)
    assert rad.max() <= shape.bounding_radius + 1e-6 and rad.max() > 0.6 * shape.bounding_radius


@pytest.mark.parametrize("name", FAMILY)
def test_kernel_matches_dense_sampling_reference(name):
    shape = make_shape(name)
    o, d = camera_rays(80, 0.7 * shape.bounding_radius, shape.center, seed=4)
    res = SdfSnellRenderer(shape).trace(o, d)
    ref = snell_sdf_numpy(shape, o, d)
    assert np.array_equal(res.status, ref.status) and np.array_equal(res.events, ref.events)
    assert (res.status == Status.EXITED).sum() > 25
    # long bounce chains amplify the 1e-12 root differences: compare the short ones tightly
    short = res.events <= 12
    assert short.sum() > 60
    assert np.abs(res.direction - ref.direction)[short].max() < 1e-7
    assert np.abs(res.surface - ref.surface)[short].max() < 1e-6


def test_float32_close_to_float64():
    shape = make_shape("bowl")
    o, d = camera_rays(3000, 15.0, shape.center, seed=6)
    a = SdfSnellRenderer(shape, precision="float64").trace(o, d)
    b = SdfSnellRenderer(shape, precision="float32").trace(o, d)
    assert (a.status == b.status).mean() > 0.99
    ok = (a.status == Status.EXITED) & (b.status == Status.EXITED)
    assert ok.sum() > 1000
    err = np.linalg.norm(a.direction - b.direction, axis=1)[ok]
    assert np.median(err) < 1e-4 and np.percentile(err, 90) < 1e-3


def test_lipschitz_bound_holds_for_the_vase():
    vase = Vase()
    rng = np.random.default_rng(5)
    p = rng.uniform(-vase.bounding_radius, vase.bounding_radius, (20000, 3)) / np.sqrt(3)
    q = p + 1e-3 * unit(rng.normal(size=p.shape))
    ratio = np.abs(vase.local_distance(q) - vase.local_distance(p)) / 1e-3
    assert ratio.max() <= vase.lipschitz
    assert vase.lipschitz < 1.5  # the normalisation keeps it near a distance


def test_random_solids_seeds_and_rebuild():
    a, a2, b = RandomSolid(seed=1), RandomSolid(seed=1), RandomSolid(seed=2)
    pts = np.random.default_rng(0).uniform(-25, 25, (2000, 3))
    assert a.capsules == a2.capsules
    assert np.array_equal(a.distance(pts), a2.distance(pts))
    assert np.abs(a.distance(pts) - b.distance(pts)).max() > 1.0
    assert make_shape("random", seed=7).capsules == RandomSolid(seed=7).capsules
    # scene.json's object rebuilds the same solid (capsules kept, not redrawn)
    c = shape_from_dict(json.loads(json.dumps(a.to_dict())))
    assert np.array_equal(c.distance(pts), a.distance(pts))
    # distance-like: 1-Lipschitz everywhere, gradient near 1 on the surface (below 1 only
    # where the smooth union blends two capsules)
    for seed in range(6):
        s = RandomSolid(seed=seed)
        assert s.inside(np.zeros((1, 3)))[0]
        p = pts[:500]
        q = p + 1e-3 * unit(np.random.default_rng(seed).normal(size=p.shape))
        assert np.abs(s.distance(q) - s.distance(p)).max() / 1e-3 <= 1 + 1e-6
        v, _ = s.mesh(spacing=1.5)
        g = np.linalg.norm(s.sdf(v)[1], axis=1)
        assert g.max() <= 1 + 1e-6 and np.median(g) > 0.9 and g.min() > 0.6
        assert 20.0 <= np.ptp(v, axis=0).max() <= 50.0


def test_other_shapes_rebuild_from_their_dict():
    pts = np.random.default_rng(1).uniform(-30, 30, (500, 3))
    for name in FAMILY:
        s = make_shape(name, eta=1.7, tilt=(5.0, -10.0, 15.0))
        t = shape_from_dict(json.loads(json.dumps(s.to_dict())))
        assert t.eta == 1.7 and t.tilt == (5.0, -10.0, 15.0)
        assert np.array_equal(s.distance(pts), t.distance(pts))


# --------------------------------------------------------------------------- errors


def _one_line_error(fn, match):
    with pytest.raises(ClrefractError, match=match) as exc:
        fn()
    assert "\n" not in str(exc.value)


def test_bad_inputs_give_one_line_errors(tmp_path, capsys):
    for eta in (2.5, 1.0, float("nan")):
        _one_line_error(lambda eta=eta: make_shape("cylinder", eta=eta), "between 1.2 and 1.9")
    _one_line_error(lambda: make_shape("teapot"), "unknown family shape 'teapot'")
    _one_line_error(lambda: Bowl(thickness=40.0), "thickness")
    _one_line_error(lambda: TwoBodies(gap=-1.0), "gap")
    _one_line_error(lambda: RandomSolid(seed=-3), "seed")
    _one_line_error(lambda: SdfSphere(radius=30.0, center=(15.0, 0.0, 0.0)), "must fit")
    out = tmp_path / "x"
    cases = [
        (["teapot"], "unknown scene 'teapot'"),
        (["vase", "--eta", "2.5"], "between 1.2 and 1.9"),
        (["vase", "--tilt", "1/2"], "--tilt must be three angles"),
        (["sphere", "--eta", "1.6"], "apply to the family shapes"),
        (["sphere", "--radius", "80"], "--radius must put the cameras outside the box"),
        (["vase", "--radius", "nan"], "--radius must put the cameras outside the box"),
        (["sphere", "--fov", "0"], "--fov must be 1 to 170 degrees"),
    ]
    for args, msg in cases:
        assert main(["dataset", "make", *args, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and "\n" not in err
    assert not out.exists()  # nothing written before the object was known


def test_dataset_make_help_lists_the_family(capsys):
    with pytest.raises(SystemExit):
        main(["dataset", "make", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in FAMILY + ("sphere", "prism", "drop"):
        assert name in text
    assert "--eta" in text and "--tilt" in text and "--radius" in text and "--fov" in text


# -------------------------------------------------------------------------- a dataset


def test_family_dataset_is_valid_and_matches_the_renderer(tmp_path):
    opt = MakeOptions(
        views=5, res=16, env_width=128, volume_res=24, seed=3, eta=1.6, tilt=(10.0, 20.0, 30.0)
    )
    info = make_dataset("random", tmp_path, opt)
    assert info["views"] == 5 and check_dataset(tmp_path) == []
    scene = json.loads((tmp_path / "scene.json").read_text())
    assert scene["object"]["kind"] == "random" and scene["object"]["seed"] == 3
    assert scene["eta_range"] == [1.0, 1.6] and scene["ground_truth"]["renderer"] == "snell-sdf"
    shape = shape_from_dict(scene["object"])
    assert shape.capsules == RandomSolid(seed=3).capsules and shape.tilt == (10.0, 20.0, 30.0)
    # the images are the SDF Snell renders through the saved environment map
    ds = Dataset(tmp_path)
    cam = ds.train[0]
    o, d = cam.rays()
    res = SdfSnellRenderer(shape).trace(o, d)
    ok = (res.status == Status.EXITED) | (res.status == Status.MISSED)
    expect = ds.envmap().lookup(res.direction)
    expect[~ok] = 0.0
    assert np.array_equal(ds.image(cam), expect.reshape(cam.height, cam.width, 3))
    # ground truth surface on the zero set, eta volume eta inside and 1 far outside
    verts, faces = read_mesh(tmp_path / "gt_surface.ply")
    assert len(faces) > 1000 and np.abs(shape.distance(verts)).max() < 1e-4  # float32 PLY
    truth = scene_truth(ds)  # what the fit's eta RMSE is measured against
    assert isinstance(truth, RandomSolid) and truth.capsules == shape.capsules
    grid = VoxelGrid.load(tmp_path / "gt_eta.npz")
    assert grid.values.max() == pytest.approx(1.6) and grid.values.min() == pytest.approx(1.0)
