"""Straight-ray baselines: density + colour fitted to the photographs without bending, rendered
by emission-absorption compositing along straight rays with the environment map behind:

- synapse: the paper's Synapse-Volumetric, density and linear colour on a fine dense node
  grid (128^3 by default, no smoothness term; kernels_cl/straight_volume.cl);
- meridian: the paper's Meridian Renderer, density and colour held in a neural field: a
  multi-resolution hash encoding and a small MLP with a 4-unit head
  (clrefract.baselines.neural, kernels_cl/straight_neural.cl). `field="grid"` gives the
  earlier stand-in instead, a coarse 48^3 grid with a smoothness penalty.

Both are trained the same way: the mean squared sRGB difference on random batches of training
rays, Adam (DenseAdam) with learning rates decaying exponentially to lr_final of the start.

A run folder holds straight.json (settings), metrics.jsonl, straight.npz (the model), run.json
(dataset and box) and is scored by `clrefract eval` like any fit.

Surface for the chamfer distance (these models have no index): clrefract.baselines.surface,
marching cubes of density at half its 99.9th percentile over nodes (the grid's, or a
surface_res^3 lattice of the neural field).
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import ClrefractError
from ..fields.base import Box
from ..imageio import atomic_path, ensure_out_dir
from ..log import Progress
from ..loss import srgb
from .surface import density_level, density_surface
from .volume import StraightRenderer, render_view

STYLES = {
    # no smoothness term on the fine grid: it cost a third of each step at 128^3, and a
    # voxel baseline is what it is without one
    "synapse": dict(field="grid", res=128, reg=0.0),
    "meridian": dict(field="neural", res=48, reg=1e-2),
}
FIELDS = ("grid", "neural")


@dataclass
class StraightConfig:
    style: str = "synapse"
    field: str = ""  # "grid" or "neural"; "": the style's
    res: int = 0  # grid nodes per axis; 0: the style's
    reg: float = -1.0  # weight of the smoothness penalty; < 0: the style's
    iterations: int = 600
    batch: int = 8192
    lr_density: float = 0.01  # per mm
    lr_colour: float = 0.02
    lr_final: float = 0.1  # learning rates decay exponentially to this fraction
    step: float = 0.0  # sample spacing, mm; 0: half a grid cell, a 64th of the box (neural)
    # the neural field: hash encoding (clrefract.fields.hashgrid's) and MLP shape
    levels: int = 6
    features: int = 2
    log2_table: int = 16
    n_min: int = 8
    n_max: int = 64
    hidden: int = 32
    layers: int = 1
    lr_table: float = 0.01
    lr_mlp: float = 0.005
    surface_res: int = 128  # nodes per axis of the density lattice the surface comes from
    precision: str = "float32"
    device: str = ""
    seed: int = 0

    def resolved(self) -> StraightConfig:
        if self.style not in STYLES:
            raise ClrefractError(f"style must be one of {', '.join(STYLES)}, got {self.style!r}")
        c = StraightConfig(**asdict(self))
        c.field = c.field or STYLES[c.style]["field"]
        if c.field not in FIELDS:
            raise ClrefractError(f"field must be one of {', '.join(FIELDS)}, got {c.field!r}")
        c.res = c.res or STYLES[c.style]["res"]
        c.reg = c.reg if c.reg >= 0 else STYLES[c.style]["reg"]
        if c.res < 2 or c.iterations < 1 or c.batch < 1 or c.surface_res < 2:
            raise ClrefractError(
                "res and surface_res must be at least 2, iterations and batch at least 1"
            )
        return c

    def hashgrid(self):
        """The neural field's encoding and MLP shape."""
        from ..fields.hashgrid import HashGridConfig

        keys = ("levels", "features", "log2_table", "n_min", "n_max", "hidden", "layers")
        return HashGridConfig(**{k: getattr(self, k) for k in keys}, interp="trilinear")


class DenseAdam:
    """Adam on a float32 array in place, with one learning rate per row of a (4, n) volume or
    per entry of a flat vector: the general clrefract.adam gathers through index arrays,
    which costs seconds per step on 128^3 x 4 values."""

    def __init__(self, shape, lr: np.ndarray, beta1=0.9, beta2=0.99, eps=1e-15):
        self.m = np.zeros(shape, np.float32)
        self.v = np.zeros(shape, np.float32)
        self.lr = np.asarray(lr, np.float32)
        if len(shape) == 2:
            self.lr = self.lr.reshape(-1, 1)
        self.b1, self.b2, self.eps, self.t = beta1, beta2, eps, 0

    def step(self, params: np.ndarray, grad: np.ndarray, lr_scale: float = 1.0) -> None:
        self.t += 1
        self.m *= self.b1
        self.m += (1 - self.b1) * grad
        self.v *= self.b2
        self.v += (1 - self.b2) * grad * grad
        denom = np.sqrt(self.v / (1 - self.b2**self.t))
        denom += self.eps
        params -= (self.lr * (lr_scale / (1 - self.b1**self.t))) * self.m / denom


def smoothness(vol: np.ndarray, res: int) -> tuple[float, np.ndarray]:
    """Mean squared difference of neighbouring nodes, per channel, and its gradient."""
    v = vol.reshape(4, res, res, res)
    grad = np.zeros(v.shape, np.float32)
    total, count = 0.0, 0
    for ax in (1, 2, 3):
        d = np.diff(v, axis=ax)
        total += float((d * d).sum())
        count += d.size
        lo, hi = [slice(None)] * 4, [slice(None)] * 4
        lo[ax], hi[ax] = slice(0, -1), slice(1, None)
        grad[tuple(lo)] -= 2 * d
        grad[tuple(hi)] += 2 * d
    return total / count, grad.reshape(-1) / count


def srgb_loss(colour: np.ndarray, target: np.ndarray, weight: np.ndarray):
    """Mean squared sRGB difference (clipped to [0, 1], as the metrics) and dLoss/dcolour."""
    enc, denc = srgb(colour)
    resid = (enc - srgb(target)[0]) * weight[:, None]
    n = max(resid.size, 1)
    return float((resid**2).sum() / n), 2 * resid * denc / n


class StraightModel:
    """A fitted straight-ray volume, for `clrefract eval`."""

    kind = "straight"
    slice_label = "density, 1/mm"

    def __init__(self, vol: np.ndarray, box: Box, res: int, step: float, runtime=None):
        self.vol, self.box, self.res = vol, box, res
        self.renderer = StraightRenderer(box, res, step, runtime=runtime)
        self.renderer.upload(vol)
        level = density_level(self.vol[0])
        self.surface_rule = (
            f"marching cubes of density at half its 99.9th percentile, {level:.4g}/mm"
        )

    @classmethod
    def load(cls, path: Path, runtime=None) -> StraightModel:
        try:
            with np.load(path, allow_pickle=False) as z:
                vol, res, step = z["volume"], int(z["res"]), float(z["step"])
                box = Box.from_dict(json.loads(str(z["box"])))
        except Exception as exc:  # noqa: BLE001 - any damage is the user's to know about
            raise ClrefractError(f"{path}: cannot read the straight-ray volume ({exc})") from None
        return cls(vol, box, res, step, runtime=runtime)

    def save(self, path: Path) -> None:
        with atomic_path(path, suffix=".npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez(  # float32, uncompressed: compressing 128^3 x 4 took seconds
                    f,
                    volume=np.asarray(self.vol, np.float32),
                    res=self.res,
                    step=self.renderer.step,
                    box=json.dumps(self.box.to_dict()),
                )

    def render(self, cam, env) -> np.ndarray:
        return render_view(self.renderer, cam, env)

    def eta(self, pts):
        return None  # no index: eta RMSE is not applicable

    def density(self, pts: np.ndarray) -> np.ndarray:
        from ..fields.voxel import interpolate

        vals = self.vol.reshape(4, self.res, self.res, self.res)[0]
        return interpolate(vals, self.box, pts, "trilinear")[0]

    slices_of = density

    def surface(self, box):
        return density_surface(self.vol.reshape(4, self.res, self.res, self.res)[0], self.box)


def load_straight(path: Path, runtime=None):
    """The model in a run's straight.npz: a grid (StraightModel) or a neural field."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if "kind" in z.files and str(z["kind"]) == "neural":
                from .neural import NeuralModel

                return NeuralModel.from_npz(path, z, runtime=runtime)
    except ClrefractError:
        raise
    except Exception as exc:  # noqa: BLE001 - any damage is the user's to know about
        raise ClrefractError(f"{path}: cannot read the straight-ray model ({exc})") from None
    return StraightModel.load(path, runtime=runtime)


def _start(cfg: StraightConfig, box: Box, runtime):
    """The model a fit starts from, its parameters (float32, updated in place) and Adam."""
    if cfg.field == "neural":
        from .neural import NeuralField, NeuralModel

        step = cfg.step or float(np.min(box.size)) / 64
        field = NeuralField(cfg.hashgrid(), box, seed=cfg.seed)
        model = NeuralModel(field, step, cfg.surface_res, runtime=runtime)
        x = field.params.astype(np.float32)
        lr = np.full(x.shape, cfg.lr_mlp, np.float32)
        lr[: field.config.n_table_params] = cfg.lr_table
        return model, x, DenseAdam(x.shape, lr)
    step = cfg.step or 0.5 * float(np.min(box.size / (cfg.res - 1)))
    x = np.zeros((4, cfg.res**3), np.float32)
    x[1:] = 0.5  # grey where the density will grow; empty space shows the background
    model = StraightModel(x, box, cfg.res, step, runtime=runtime)
    return model, x, DenseAdam(x.shape, np.array([cfg.lr_density] + [cfg.lr_colour] * 3))


def fit_straight(dataset: Path, out: Path, cfg: StraightConfig, stream=None) -> dict:
    """Fit a straight-ray volume to a dataset's training views; returns the run summary."""
    from ..dataset import Dataset
    from ..runtime import Runtime

    cfg = cfg.resolved()
    stream = stream or sys.stderr
    out = Path(out)
    if (out / "straight.npz").exists() or (out / "field.npz").exists():
        raise ClrefractError(f"{out} already holds a run; use another folder")
    ensure_out_dir(out, "run folder")
    ds = Dataset(dataset)
    box = ds.box
    runtime = Runtime(cfg.device or None)
    origins, dirs, rgb = ds.rays_and_pixels("train")
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    weights = ds.pixel_weights("train")
    bg = ds.envmap().lookup(dirs).astype(np.float64)
    model, x, adam = _start(cfg, box, runtime)
    (out / "straight.json").write_text(json.dumps(asdict(cfg), indent=2))
    (out / "run.json").write_text(
        json.dumps({"dataset": str(Path(dataset).resolve()), "box": box.to_dict()}, indent=2)
    )
    rng = np.random.default_rng(cfg.seed)
    bar = Progress(cfg.iterations, f"fit {cfg.style}", unit="it", stream=stream)
    t_start = time.perf_counter()
    losses = []
    with (out / "metrics.jsonl").open("w") as mf:
        for it in range(cfg.iterations):
            t0 = time.perf_counter()
            idx = rng.integers(0, len(origins), size=min(cfg.batch, len(origins)))
            o, d, b = origins[idx], dirs[idx], bg[idx]
            colour, _ = model.renderer.render(o, d, b)
            loss, dl_dc = srgb_loss(colour, rgb[idx], weights[idx])
            grad = model.renderer.backward(o, d, b, colour, dl_dc)
            grad = grad.astype(np.float32).reshape(x.shape)
            reg = 0.0
            if cfg.field == "grid" and cfg.reg > 0:
                reg, greg = smoothness(x, cfg.res)
                grad += cfg.reg * greg.reshape(x.shape)
            adam.step(x, grad, lr_scale=cfg.lr_final ** (it / cfg.iterations))
            if cfg.field == "grid":
                np.clip(x, 0.0, None, out=x)  # density and colour are non-negative
            model.renderer.upload(x)
            losses.append(loss)
            m = {"iteration": it + 1, "loss": loss, "reg": reg}
            m["seconds"] = time.perf_counter() - t0
            mf.write(json.dumps(m) + "\n")
            bar.update(1, loss=loss)
    model.save(out / "straight.npz")
    return {
        "style": cfg.style,
        "iterations": cfg.iterations,
        "first_loss": losses[0],
        "final_loss": losses[-1],
        "train_seconds": time.perf_counter() - t_start,
    }
