"""The speed/accuracy trade study (`clrefract bench`, issue 12): per scene, integrator,
precision and step (or tolerance), what each configuration costs and what it gets wrong.

Columns of a row:
- exit-direction error, largest and median, over a bundle of parallel rays, against the
  Luneburg closed form, else float64 Dormand-Prince at tol 1e-11;
- image PSNR of one view against the same reference renderer (200 dB: identical);
- gradient error (rkn4 rows of fields with parameters: the voxel scene): the relative error
  of the adjoint's directional derivative of the photometric loss, along the field's own
  bump, against central differences of the float64 loss at a quarter of the finest step;
- device bytes: the buffers one trace of the bundle used (field, rays, results);
- rays per second, ray-steps per second and field evaluations per ray (build excluded).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .fields.analytic import Blobs, Luneburg, Sphere
from .fields.base import Box
from .tracer import EVALS_PER_STEP, Status, Tracer, TraceSettings, renders_black

PSNR_CAP = 200.0  # dB written for an image identical to the reference
REF_TOL = 1e-11  # float64 Dormand-Prince: agrees with RK4 at 0.02 mm to ~1e-9


def _voxel_blob():
    from .fields.voxel import VoxelGrid

    # a smooth bump on a coarse grid: the parametric field whose gradient the study checks
    bump = Blobs(centers=[[0, 0, 0], [5, -4, 3]], amplitudes=[0.05, 0.03], sigmas=[9.0, 6.0])
    return VoxelGrid.from_field(bump, Box((-30.0,) * 3, (30.0,) * 3, 4.0), 16, "bspline")


SCENES = {
    "sphere": lambda: Sphere(radius=20.0, eta=1.5, width=1.0),
    "luneburg": lambda: Luneburg(radius=20.0),
    # compact enough to be 1 at the box walls (the tracer's contract)
    "plume": lambda: Blobs(
        centers=[[0, 0, 0], [6, -4, 3], [-5, 5, -2]],
        amplitudes=[2e-3, 1e-3, 1.5e-3],
        sigmas=[6.0, 4.0, 5.0],
    ),
    "voxel": _voxel_blob,
}


@dataclass
class Size:
    rays: int
    image: int  # pixels across the PSNR view
    repeats: int  # timed traces, the fastest kept
    scenes: tuple
    fixed: dict  # integrator -> steps (mm)
    tols: list  # dopri5 tolerances
    precisions: tuple = ("float32", "float64")
    extra: dict = field(default_factory=dict)


SIZES = {
    "full": Size(
        rays=2048,
        image=64,
        repeats=2,
        scenes=tuple(SCENES),
        fixed={
            "rkn4": [2.0, 1.0, 0.5, 0.25, 0.125],
            "rk4": [2.0, 1.0, 0.5, 0.25, 0.125],
            "euler": [0.5, 0.125, 0.03125],
        },
        tols=[1e-4, 1e-6, 1e-8, 1e-10],
    ),
    # about a minute on 2 CPU cores
    "quick": Size(
        rays=512,
        image=32,
        repeats=3,
        scenes=("sphere", "luneburg", "voxel"),
        fixed={"rkn4": [2.0, 1.0, 0.5, 0.25], "rk4": [1.0, 0.25], "euler": [0.25]},
        tols=[1e-4, 1e-7],
    ),
}


def bundle(n: int, radius: float = 18.0, seed: int = 0):
    """n parallel rays along +x, spread uniformly over a disc of the radius."""
    rng = np.random.default_rng(seed)
    b = radius * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    yz = np.column_stack([b * np.cos(phi), b * np.sin(phi)])
    return np.column_stack([np.full(n, -120.0), yz]), np.tile([1.0, 0.0, 0.0], (n, 1))


class Scene:
    """One field with its references: exit directions of the bundle, one rendered view,
    and (fields with parameters) the loss setting of the gradient check."""

    def __init__(self, name: str, size: Size, runtime):
        from .cameras import fibonacci_sphere_cameras
        from .envmap import EnvMap

        self.name, self.runtime = name, runtime
        self.field = SCENES[name]()
        self.box = self.field.tracing_box(Box())
        self.o, self.d = bundle(size.rays)
        n = size.image
        self.camera = fibonacci_sphere_cameras(1, radius=100.0, width=n, height=n)[0]
        self.env = EnvMap.procedural(seed=0)
        ref = self.tracer(integrator="dopri5", step=2.0, tol=REF_TOL, precision="float64")
        if name == "luneburg":  # closed form: every ray leaves through the antipode of its entry
            r = self.field.radius
            p = np.column_stack([-np.sqrt(r**2 - (self.o[:, 1:] ** 2).sum(1)), self.o[:, 1:]])
            self.ref_dir = -p / r
        else:
            self.ref_dir = ref.trace(self.o, self.d).direction
        self.ref_image = self.render(ref)
        self.grad = None

    def tracer(self, **kw) -> Tracer:
        return Tracer(self.field, self.box, TraceSettings(**kw), runtime=self.runtime)

    def render(self, tracer: Tracer) -> np.ndarray:
        from .render import render_camera

        return render_camera(tracer, self.camera, self.env).image

    def gradient_check(self, finest: float):
        """The setting of the gradient column: parameters at 70% of the bump, targets the
        bump's own rendering, the direction the bump itself, and the float64 finite
        difference of the loss at a quarter of the finest step."""
        if self.grad is None:
            from .gradcheck import smooth_env
            from .gradient import traced_loss

            truth = np.array(self.field.data(), np.float64)
            u = (truth - 1) / np.abs(truth - 1).max()
            p0 = truth - 0.3 * (truth - 1)
            env = smooth_env(1024)
            fine = self.tracer(integrator="rkn4", step=finest / 4, precision="float64")
            target = env.lookup(fine.trace(self.o, self.d).direction)

            def loss(p):
                self.field.set_data(p)
                fine.upload_field()
                r = fine.trace(self.o, self.d)
                return traced_loss(env, r.status, r.last_velocity, target)[0]

            # the bilinear environment has a kink at every texel edge: a ray that crosses one
            # within the difference spoils it (512 rays: 2e-5 relative at 1e-7, 2e-9 at 1e-8,
            # the float64 rounding still far below the adjoint's errors)
            eps = 1e-8
            fd = (loss(p0 + eps * u) - loss(p0 - eps * u)) / (2 * eps)
            self.field.set_data(truth)
            self.grad = (truth, p0, u, env, target, fd)
        return self.grad

    def gradient_error(self, step: float, precision: str, finest: float) -> float:
        from .gradient import GradientEngine

        truth, p0, u, env, target, fd = self.gradient_check(finest)
        settings = TraceSettings(step=step, precision=precision)
        eng = GradientEngine(self.field, self.box, settings, runtime=self.runtime)
        try:
            eng.set_params(p0)
            g = eng.loss_and_grad(self.o, self.d, target, env).grad
        finally:
            self.field.set_data(truth)
        return float(abs(g @ u - fd) / abs(fd))


def measure(scene: Scene, repeats: int, finest: float, **kw) -> dict:
    from .metrics import psnr_ssim

    tr = scene.tracer(**kw)
    tr.trace(scene.o, scene.d)  # build, and PoCL specialises per launch size: not timed
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = tr.trace(scene.o, scene.d)
        best = min(best, time.perf_counter() - t0)
    nbytes = tr.launch_bytes
    err = np.linalg.norm(res.direction - scene.ref_dir, axis=1)
    err[renders_black(res.status)] = 2.0  # a lost ray is as wrong as a direction can be
    steps = float(res.steps.mean())
    psnr = psnr_ssim(scene.render(tr), scene.ref_image)[0]
    grad = None
    if kw["integrator"] == "rkn4" and getattr(scene.field, "adjoint_source", None):
        grad = scene.gradient_error(kw["step"], kw["precision"], finest)
    return {
        "error_max": float(err.max()),
        "error_median": float(np.median(err)),
        "exited": float(np.mean(res.status == Status.EXITED)),
        "psnr_db": float(min(psnr, PSNR_CAP)),
        "grad_error": grad,
        "device_bytes": int(nbytes),
        "steps_per_ray": steps,
        "evals_per_ray": steps * EVALS_PER_STEP[kw["integrator"]],
        "rays_per_s": len(scene.o) / best,
        "ray_steps_per_s": len(scene.o) * steps / best,
        "seconds": best,
    }


def configurations(size: Size, precision: str) -> list[dict]:
    cfgs = [dict(integrator=i, step=h) for i, hs in size.fixed.items() for h in hs]
    cfgs += [dict(integrator="dopri5", step=4.0, tol=t) for t in size.tols]
    # below float32's rounding the adaptive step never passes: the tracer refuses it
    return [c for c in cfgs if not (precision == "float32" and c.get("tol", 1) < 1e-9)]


def run_study(size: Size, runtime=None, log=None) -> list[dict]:
    from .runtime import default_runtime

    runtime = runtime or default_runtime()
    finest = min([h for hs in size.fixed.values() for h in hs], default=0.25)
    rows = []
    for name in size.scenes:
        scene = Scene(name, size, runtime)
        for precision in size.precisions:
            if precision == "float64" and not runtime.info.fp64:
                continue
            for cfg in configurations(size, precision):
                r = {"scene": name, "precision": precision, "tol": None, **cfg}
                r.update(measure(scene, size.repeats, finest, precision=precision, **cfg))
                rows.append(r)
                if log:
                    log(table_line(r))
    return rows


COLUMNS = (
    "scene",
    "precision",
    "integrator",
    "step or tol",
    "exit err max",
    "exit err median",
    "PSNR dB",
    "grad err",
    "device KiB",
    "rays/s",
    "ray-steps/s",
    "evals/ray",
)


def _cells(r: dict) -> list[str]:
    what = f"tol {r['tol']:g}" if r["tol"] is not None else f"{r['step']:g} mm"
    return [
        r["scene"],
        r["precision"],
        r["integrator"],
        what,
        f"{r['error_max']:.1e}",
        f"{r['error_median']:.1e}",
        f"{r['psnr_db']:.1f}",
        "-" if r["grad_error"] is None else f"{r['grad_error']:.1e}",
        f"{r['device_bytes'] / 1024:.0f}",
        f"{r['rays_per_s']:.0f}",
        f"{r['ray_steps_per_s']:.2e}",
        f"{r['evals_per_ray']:.0f}",
    ]


def table_line(r: dict) -> str:
    return "| " + " | ".join(_cells(r)) + " |"


def markdown(rows: list[dict]) -> str:
    head = "| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS) + "\n"
    return head + "".join(table_line(r) + "\n" for r in rows)


def pareto(rows):
    """Rows not beaten in both error and speed by another row."""
    return [
        r
        for r in rows
        if not any(
            s["error_max"] <= r["error_max"]
            and s["rays_per_s"] >= r["rays_per_s"]
            and (s["error_max"] < r["error_max"] or s["rays_per_s"] > r["rays_per_s"])
            for s in rows
        )
    ]


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = plt.subplots(1, len(scenes), figsize=(5.2 * len(scenes), 4.6), squeeze=False)
    colours = {"rkn4": "C0", "rk4": "C1", "euler": "C2", "dopri5": "C3"}
    for ax, name in zip(axes[0], scenes):
        sub = [r for r in rows if r["scene"] == name]
        for r in sub:
            ax.scatter(
                r["rays_per_s"],
                max(r["error_max"], 1e-13),
                color=colours[r["integrator"]],
                marker="o" if r["precision"] == "float32" else "^",
                s=22,
                alpha=0.8,
            )
        front = sorted(pareto(sub), key=lambda r: r["rays_per_s"])
        ax.plot(
            [r["rays_per_s"] for r in front],
            [max(r["error_max"], 1e-13) for r in front],
            "k--",
            lw=0.8,
        )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("rays per second")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("max exit-direction error")
    for i, c in colours.items():
        axes[0][0].scatter([], [], color=c, label=i)
    axes[0][0].scatter([], [], color="grey", marker="o", label="float32")
    axes[0][0].scatter([], [], color="grey", marker="^", label="float64")
    axes[0][0].plot([], [], "k--", lw=0.8, label="Pareto front")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_study(rows: list[dict], out: Path) -> dict:
    """tradeoff.md, tradeoff.json and tradeoff.png in the folder out."""
    paths = {ext: out / f"tradeoff.{ext}" for ext in ("md", "json", "png")}
    paths["md"].write_text(markdown(rows))
    paths["json"].write_text(json.dumps(rows, indent=1))
    plot(rows, paths["png"])
    return paths
