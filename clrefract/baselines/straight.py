"""Straight-ray baselines: density + colour volumes fitted to the photographs without bending.

Both keep density and linear colour on a dense node grid and render it by emission-absorption
compositing along straight rays, the environment map behind (kernels_cl/straight_volume.cl):

- synapse: the paper's Synapse-Volumetric, a fine voxel grid (128^3 by default, no
  smoothness term);
- meridian: the paper's Meridian Renderer holds density and colour in a neural field. Here it
  is a coarse dense grid (48^3 by default) with a stronger smoothness penalty standing in for a
  small field's smooth output: NOT a neural network (an honest simplification; the renderer,
  straight-ray volume marching with the environment behind, is the part the comparison is
  about).

A run folder holds straight.json (settings), metrics.jsonl, straight.npz (the volume), run.json
(dataset and box) and is scored by `clrefract eval` like any fit.

Surface for the chamfer distance (these models have no index): marching cubes of density at
half its 99.9th percentile over the grid's nodes. A fixed absorption level (ln 2 per cell, say)
depends on the grid and was never reached by fits that render glass as a thin, faint shell;
the percentile keeps a few floaters from setting the level.
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
from ..loss import srgb
from ..progress import Progress
from .volume import StraightRenderer

STYLES = {
    # no smoothness term on the fine grid: it cost a third of each step at 128^3, and a
    # voxel baseline is what it is without one
    "synapse": dict(res=128, reg=0.0),
    "meridian": dict(res=48, reg=1e-2),
}


@dataclass
class StraightConfig:
    style: str = "synapse"
    res: int = 0  # 0: the style's
    reg: float = -1.0  # weight of the smoothness penalty; < 0: the style's
    iterations: int = 600
    batch: int = 8192
    lr_density: float = 0.01  # per mm
    lr_colour: float = 0.02
    lr_final: float = 0.1  # learning rates decay exponentially to this fraction
    step: float = 0.0  # sample spacing, mm; 0: half a cell
    precision: str = "float32"
    device: str = ""
    seed: int = 0

    def resolved(self) -> StraightConfig:
        if self.style not in STYLES:
            raise ClrefractError(f"style must be one of {', '.join(STYLES)}, got {self.style!r}")
        c = StraightConfig(**asdict(self))
        c.res = c.res or STYLES[c.style]["res"]
        c.reg = c.reg if c.reg >= 0 else STYLES[c.style]["reg"]
        if c.res < 2 or c.iterations < 1 or c.batch < 1:
            raise ClrefractError("res must be at least 2, iterations and batch at least 1")
        return c


class DenseAdam:
    """Adam on a (4, n) float32 volume with one learning rate per channel, in place: the
    general clrefract.adam gathers through index arrays, which costs seconds per step on
    128^3 x 4 values."""

    def __init__(self, shape, lr: np.ndarray, beta1=0.9, beta2=0.99, eps=1e-15):
        self.m = np.zeros(shape, np.float32)
        self.v = np.zeros(shape, np.float32)
        self.lr = np.asarray(lr, np.float32).reshape(-1, 1)
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


def density_level(density: np.ndarray) -> float:
    """The documented surface rule: half the density's 99.9th percentile over the nodes."""
    return 0.5 * float(np.percentile(density, 99.9))


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
        o, d = cam.rays()
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        rgb = np.empty((len(o), 3))
        for s in range(0, len(o), 1 << 18):
            sl = slice(s, s + (1 << 18))
            rgb[sl] = self.renderer.render(o[sl], d[sl], env.lookup(d[sl]))[0]
        return rgb.reshape(cam.height, cam.width, 3)

    def eta(self, pts):
        return None  # no index: eta RMSE is not applicable

    def density(self, pts: np.ndarray) -> np.ndarray:
        from ..fields.voxel import interpolate

        vals = self.vol.reshape(4, self.res, self.res, self.res)[0]
        return interpolate(vals, self.box, pts, "trilinear")[0]

    slices_of = density

    def surface(self, box):
        from skimage.measure import marching_cubes

        vol = self.vol.reshape(4, self.res, self.res, self.res)[0]
        level = density_level(vol)
        if not (level > 0 and vol.min() < level < vol.max()):
            return None
        spacing = tuple(float(h) for h in self.box.size / (self.res - 1))
        verts, faces, _, _ = marching_cubes(vol, level, spacing=spacing)
        return verts + np.asarray(self.box.lo), faces


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
    step = cfg.step or 0.5 * float(np.min(box.size / (cfg.res - 1)))
    origins, dirs, rgb = ds.rays_and_pixels("train")
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    weights = ds.pixel_weights("train")
    bg = ds.envmap().lookup(dirs).astype(np.float64)
    vol = np.zeros((4, cfg.res**3), np.float32)
    vol[1:] = 0.5  # grey where the density will grow; empty space shows the background
    model = StraightModel(vol, box, cfg.res, step, runtime=runtime)
    lrs = [cfg.lr_density] + [cfg.lr_colour] * 3
    adam = DenseAdam(vol.shape, np.array(lrs))
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
            colour, _ = model.renderer.render(origins[idx], dirs[idx], bg[idx])
            loss, dl_dc = srgb_loss(colour, rgb[idx], weights[idx])
            grad = model.renderer.backward(origins[idx], dirs[idx], bg[idx], colour, dl_dc)
            grad = grad.astype(np.float32).reshape(vol.shape)
            reg = 0.0
            if cfg.reg > 0:
                reg, greg = smoothness(vol, cfg.res)
                grad += cfg.reg * greg.reshape(vol.shape)
            adam.step(vol, grad, lr_scale=cfg.lr_final ** (it / cfg.iterations))
            np.clip(vol, 0.0, None, out=vol)  # density and colour are non-negative
            model.renderer.upload(vol)
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
