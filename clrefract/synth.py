"""`clrefract dataset make`: the synthetic refractive benchmark (SPEC section 5).

Solid objects (sphere, prism, drop) are rendered by exact Snell refraction at their analytic
surfaces (clrefract.snell), the family shapes (rounded cube, cylinder, bowl, two bodies, vase,
random solids, cut stones; clrefract.family) by exact Snell refraction at their signed-distance
surfaces (clrefract.snell_sdf), never by the eikonal tracer that fitting uses; graded-index
scenes by the eikonal tracer in float64 with a fine step:

- luneburg: the Luneburg lens, radius 20 mm, index sqrt(2) at its centre;
- blobs: five Gaussian blobs drawn by --seed (amplitudes 0.08-0.16, sigmas 5-8 mm, centres
  within 16 mm of the box centre): a peak index of about 1.1 to 1.4;
- grin-rod: a parabolic (Selfoc) rod, index 1.2 on its axis falling to 1 at its radius 12 mm,
  50 mm long with C2 end caps, its axis tilted 30 degrees from z;
- grin-lens: an axial graded-index disc, radius 20 mm, 12 mm thick, index 1.4 on its
  mid-plane falling to 1 at its faces and rim, tilted;
- plume: a buoyant plume rising along z, eta - 1 about 1e-3 at its 2 mm wide base, widening
  and fading with height, meandering a little.

Graded-index glass (a sharp surface, a graded interior; fields/interior.py), rendered by the
interface tracer in float64 with steps of 0.1 mm inside (its exit directions agree with
SciPy's DOP853 to 1e-9 rad, tests/test_interior.py):

- grin-ball: a ball of radius 18 mm, index 1.6 at its centre falling radially to 1.5 at its
  surface, with a gradient of 0.04 along z;
- grin-stone: a seeded cut stone (as `faceted`) holding a seeded quadratic index, 1.45 to 1.65
  at its centre, varying by up to about 0.1 inside.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cameras import fibonacci_sphere_cameras, save_transforms
from .dataset import Scene, write_scene
from .envmap import EnvMap, rotation_matrix
from .errors import ClrefractError
from .family import FAMILY, make_shape
from .fields.analytic import Blobs, Drop, GrinLens, GrinRod, Luneburg, Plume, Prism, Sphere
from .fields.base import Box
from .imageio import write_exr_rgb, write_png_srgb
from .log import Progress
from .mesh import write_mesh
from .realistic import Flaws, RealisticCapture

SOLIDS = ("sphere", "prism", "drop")
GRADED = ("luneburg", "blobs", "grin-rod", "grin-lens", "plume")
GRADED_GLASS = ("grin-ball", "grin-stone")
SCENES = SOLIDS + GRADED + FAMILY + GRADED_GLASS
GRADED_GLASS_STEP = 0.1  # mm, the reference's RK4 step inside


def graded_glass(name: str, seed: int):
    """The graded-index glass scenes (GRADED_GLASS)."""
    from .family import Faceted, corner_radius
    from .fields.interface import PolytopeInterface, SphereInterface
    from .fields.interior import GradedInterface

    if name == "grin-ball":  # eta = 1.6 - 0.1 (r / R)^2 + 0.02 z / R
        ball = SphereInterface((0.0, 0.0, 0.0), 18.0, 1.6)
        terms = [0.0, 0.0, 0.02, -0.1, -0.1, -0.1, 0.0, 0.0, 0.0]
        return GradedInterface(ball, terms, (0.0, 0.0, 0.0), 18.0, GRADED_GLASS_STEP)
    faces = np.asarray(Faceted(seed=seed).faces, float)
    stone = PolytopeInterface(faces, 1.0, Box(), (0.0, 0.0, 0.0))
    rng = np.random.default_rng(seed + 7919)  # not the faces' stream
    scale = float(corner_radius(faces))  # u within the unit ball
    stone.set_data(np.append(stone.planes.ravel(), rng.uniform(1.45, 1.65)))
    terms = np.concatenate(
        [rng.uniform(-0.03, 0.03, 3), rng.uniform(-0.08, 0.0, 3), rng.uniform(-0.02, 0.02, 3)]
    )
    return GradedInterface(stone, terms, (0.0, 0.0, 0.0), scale, GRADED_GLASS_STEP)


def scene_object(name: str, eta: float | None = None, tilt=None, seed: int | None = None):
    """The analytic object of a benchmark scene (its interface width is only used to draw
    the ground-truth eta volume; the images use the sharp surface). eta and tilt choose those
    of a family shape, seed draws the `random`, `faceted` and `grin-stone` ones and the
    `blobs` cluster; the other scenes are fixed."""
    if name in FAMILY:
        return make_shape(name, eta=eta, tilt=tilt, seed=seed)
    if name in SCENES and (eta is not None or tilt is not None):
        raise ClrefractError(
            f"--eta and --tilt apply to the family shapes ({', '.join(FAMILY)}), not to {name}"
        )
    if name == "sphere":
        return Sphere(radius=20.0, eta=1.5, width=0.8)
    if name == "prism":
        return Prism(side=40.0, length=40.0, eta=1.5, width=0.8, tilt=(35.0, 20.0, 10.0))
    if name == "drop":
        return Drop(R=18.0, H=22.0, eta=1.33, width=0.8)
    if name == "luneburg":
        return Luneburg(radius=20.0)
    if name == "blobs":
        # every blob 34 mm (4.25 sigma) or more from the walls: eta - 1 there stays below
        # 5 x 0.16 exp(-34^2 / 2 8^2) < 1e-4 whatever the seed
        return Blobs.random(5, amplitude=0.16, seed=seed or 0, extent=16.0, sigmas=(5.0, 8.0))
    if name == "grin-rod":
        return GrinRod(n0=1.2, radius=12.0, length=50.0, cap=8.0, tilt=(0.0, 30.0, 0.0))
    if name == "grin-lens":
        return GrinLens(dn=0.4, radius=20.0, thickness=12.0, rim=4.0, tilt=(40.0, 25.0, 0.0))
    if name in GRADED_GLASS:
        return graded_glass(name, seed or 0)
    if name == "plume":
        return Plume(
            amplitude=1e-3, sigma0=2.0, spread=0.08, half_height=35.0, center=(0.0, 0.0, 5.0)
        )
    raise ClrefractError(f"unknown scene {name!r}; scenes are {', '.join(SCENES)}")


@dataclass
class MakeOptions:
    views: int = 100
    res: int = 128
    test_every: int = 5
    seed: int = 0
    envmap: str | None = None  # a user's EXR instead of the procedural map
    env_width: int = 2048
    radius: float = 200.0
    fov_y: float = 30.0
    device: str | None = None
    volume_res: int = 128
    eta: float | None = None  # family shapes: index of the glass (default 1.5)
    tilt: tuple[float, float, float] | None = None  # family shapes: rotation, degrees
    # the panorama turned in the world (scene.json's envmap_rotation): tests of its registration
    env_rotation: list | None = None
    realistic: Flaws | None = None  # render a real capture's flaws (clrefract.realistic)


def _ray_renderer(name: str, obj, box: Box, runtime):
    """A function (origins, dirs) -> (exit directions, ok mask)."""
    from .tracer import Status, Tracer, TraceSettings

    if name in GRADED_GLASS:
        from .interface import InterfaceTracer

        renderer = InterfaceTracer(obj, box, TraceSettings(precision="float64"), runtime=runtime)
    elif name in FAMILY or name in SOLIDS:
        from .snell import SnellRenderer
        from .snell_sdf import SdfSnellRenderer

        cls = SdfSnellRenderer if name in FAMILY else SnellRenderer
        renderer = cls(obj, box, precision="float64", runtime=runtime)
    else:
        settings = TraceSettings(step=0.05, integrator="rkn4", precision="float64", max_steps=20000)
        renderer = Tracer(obj, box, settings, runtime=runtime)

    def trace(o, d):
        r = renderer.trace(o, d)
        return r.direction, (r.status == Status.EXITED) | (r.status == Status.MISSED)

    return trace


def surface_mesh(obj, spacing: float = 0.4):
    """Marching cubes of the object's sharp surface: the signed distance for solids, the
    level halfway between 1 and the peak index for graded scenes. Family shapes mesh
    themselves (on their own bounding cube, vertices projected onto the zero set)."""
    from skimage.measure import marching_cubes

    if hasattr(obj, "mesh"):
        return obj.mesh()
    ext = 32.0
    n = int(2 * ext / spacing) + 1
    ax = np.linspace(-ext, ext, n)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    if hasattr(obj, "sdf"):
        vol, level = obj.sdf(pts)[0].reshape(n, n, n), 0.0
    else:
        eta = obj.eval(pts)[0].reshape(n, n, n)
        vol, level = -eta, -(1 + (eta.max() - 1) / 2)
    verts, faces, _, _ = marching_cubes(vol, level, spacing=(spacing,) * 3)
    return verts - ext, faces


def make_dataset(name: str, out: Path, opt: MakeOptions, stream=None, obj=None) -> dict:
    """Write the dataset of a benchmark scene (or of `obj`, any analytic field, rendered as a
    graded-index scene under the name `name`)."""
    from .fields.voxel import VoxelGrid
    from .runtime import Runtime

    t_start = time.perf_counter()
    if obj is None:
        obj = scene_object(name, eta=opt.eta, tilt=opt.tilt, seed=opt.seed)
    box = Box()
    reach = float(np.linalg.norm(box.size)) / 2
    if not reach < opt.radius < 1e6:
        raise ClrefractError(
            f"--radius must put the cameras outside the box: more than {reach:.1f} mm "
            f"(its half diagonal), got {opt.radius:g}"
        )
    if not 1.0 <= opt.fov_y <= 170.0:
        raise ClrefractError(f"--fov must be 1 to 170 degrees, got {opt.fov_y:g}")
    if opt.realistic is not None and opt.res >= 4:
        opt.realistic.check(fibonacci_sphere_cameras(1, opt.radius, opt.res, opt.res, opt.fov_y)[0])
    out = Path(out)
    (out / "train").mkdir(parents=True, exist_ok=True)
    (out / "test").mkdir(parents=True, exist_ok=True)
    if opt.views < 2 or opt.res < 4 or opt.test_every < 2:
        raise ClrefractError("need at least 2 views, 4 pixels and --test-every >= 2")
    env = (
        EnvMap.from_exr(opt.envmap)
        if opt.envmap
        else EnvMap.procedural(opt.env_width, opt.env_width // 2, seed=opt.seed)
    )
    env.save(out / "envmap.exr")
    write_png_srgb(out / "envmap.png", env.image)
    if opt.env_rotation is not None:
        env = EnvMap(env.image, rotation_matrix(opt.env_rotation))
    capture = None if opt.realistic is None else RealisticCapture(opt.realistic, env, opt.seed)
    runtime = Runtime(opt.device)
    trace = _ray_renderer(name if name in SCENES else "graded", obj, box, runtime)
    cams = fibonacci_sphere_cameras(
        opt.views, radius=opt.radius, width=opt.res, height=opt.res, fov_y_deg=opt.fov_y
    )
    if capture is not None:  # rays leave through its lens, from the true poses
        cams, env = [capture.lens(c) for c in cams], capture.env
    train, test = [], []
    bar = Progress(opt.views, f"dataset {name}", unit="views", stream=stream)
    bad_total = 0
    for k, cam in enumerate(cams):
        split = "test" if k % opt.test_every == 0 else "train"
        cam.file_path = f"./{split}/r_{k:03d}"
        cam.name = f"r_{k:03d}"
        o, d = cam.rays()
        exit_dir, ok = trace(o, d)
        img = env.lookup(exit_dir)
        img[~ok] = 0.0  # rays trapped by total internal reflection carry no light here
        bad_total += int((~ok).sum())
        img = img.reshape(cam.height, cam.width, 3)
        if capture is None:
            write_exr_rgb(out / split / f"r_{k:03d}.exr", img)
            write_png_srgb(out / split / f"r_{k:03d}.png", img)
        else:  # the camera its transforms file records
            cam = capture.shoot(k, cam, img, out / split / f"r_{k:03d}", split)
        (test if split == "test" else train).append(cam)
        bar.update(1)
    save_transforms(out / "transforms_train.json", train)
    save_transforms(out / "transforms_test.json", test)
    if capture is not None:
        capture.save(out)
    t_views = time.perf_counter() - t_start
    VoxelGrid.from_field(obj, box, opt.volume_res, "trilinear").save(out / "gt_eta.npz")
    verts, faces = surface_mesh(obj)
    write_mesh(out / "gt_surface.ply", verts, faces)
    eta_hi = float(obj.eta_max)
    scene = Scene(
        box=box,
        eta_range=(1.0, eta_hi),
        object=obj.to_dict(),
        envmap_rotation=None if opt.env_rotation is None else list(opt.env_rotation),
        ground_truth={
            "eta_volume": "gt_eta.npz",
            "surface": "gt_surface.ply",
            "renderer": (
                "snell"
                if name in SOLIDS
                else "snell-sdf"
                if name in FAMILY
                else "interface-f64"
                if name in GRADED_GLASS
                else "eikonal-f64"
            ),
        },
        extra={
            "name": name,
            "seed": opt.seed,
            "views": opt.views,
            "res": opt.res,
            "test_every": opt.test_every,
            "untraced_pixels": bad_total,
        },
    )
    write_scene(out, scene)
    return {
        "scene": name,
        "views": opt.views,
        "res": opt.res,
        "seconds_views": t_views,
        "seconds_total": time.perf_counter() - t_start,
        "untraced_pixels": bad_total,
        **({"realistic": capture.summary()} if capture is not None else {}),
    }
