"""The photometric objective: the loss of training rays, with its adjoint gradient, and the
held-out loss that picks the field a run keeps."""

from __future__ import annotations

import numpy as np

from ..loss import SPACES
from .rays import Tag, TrainingRays


def loss_space(setting: str, ds) -> str:
    """The loss's colour space: the setting, or where it leaves it to the frames (auto),
    srgb420 for JPEGs that store colour per 2 x 2 block, else srgb."""
    if setting in SPACES:
        return setting
    return "srgb420" if ds.chroma_halved() else "srgb"


class Objective:
    """Losses of a field's rays against the training pixels (`cfg.loss`'s colour space)."""

    def __init__(self, rays: TrainingRays, loss_space: str, batch: int, seed: int, centres=None):
        self.rays, self.space = rays, loss_space
        self.batch, self.seed = batch, seed
        self.centres = centres  # centres.CameraCentres where the cameras' centres are fitted
        self._held_idx = None

    def origins(self, idx: np.ndarray) -> np.ndarray:
        """The rays' origins, from the cameras' centres as fitted so far."""
        o = self.rays.origins[idx]
        return o if self.centres is None else o + self.centres.offsets(idx)

    def _compared(self, idx: np.ndarray, group: int = 1) -> np.ndarray:
        """The rays that stand for idx: under the srgb420 loss, whole 2 x 2 blocks (as many
        rays), unless they come in larger blocks already."""
        return self.rays.chroma_blocks(idx) if self.space == "srgb420" and group == 1 else idx

    def render(self, tracer, idx: np.ndarray) -> tuple[float, np.ndarray]:
        """The loss of rays idx against the sharp environment (forward pass only), and the
        radiance of each ray compared (linear RGB, black where trapped)."""
        from ..gradient import traced_loss

        r = self.rays
        idx = self._compared(idx)
        t = tracer.trace(self.origins(idx), r.dirs[idx])
        loss, _, radiance = traced_loss(
            r.env, t.status, t.direction, r.rgb[idx], r.weights[idx], self.space
        )
        return loss, radiance

    def loss(self, tracer, idx: np.ndarray) -> float:
        return self.render(tracer, idx)[0]

    def loss_and_grad(
        self, engine, idx: np.ndarray, it: int | None = None, group: int = 1, step=None
    ):
        """The loss and adjoint gradient of rays idx; against the images and environment
        blurred as at iteration `it` (None: sharp). `step`: the training step whose gradient
        this is, which moves fitted camera centres (None: they stay)."""
        r = self.rays
        idx = self._compared(idx, group)
        env, targets = r.blurred(it) if it is not None else (r.env, r.rgb)
        res = engine.loss_and_grad(
            self.origins(idx), r.dirs[idx], targets[idx], env, r.weights[idx], group
        )
        res.rays = idx  # under srgb420, the 2 x 2 blocks, not the rays asked for
        if self.centres is not None and step is not None and res.origin_grad is not None:
            self.centres.step(idx, res.origin_grad, step)
        return res

    def held_out_idx(self) -> np.ndarray:
        """A fixed batch of the held-out views' rays, most through their masks (elsewhere
        every field near the hull renders alike); training rays without held-out views."""
        r = self.rays
        if len(r.held) == 0:
            return r.fixed_batch(Tag.VALIDATION)
        if self._held_idx is None:
            rng = np.random.default_rng([self.seed, *Tag.VALIDATION])
            marked = np.intersect1d(r.marked(), r.held, assume_unique=True)
            size = min(self.batch, len(r.held))
            k = min(len(marked), size * 3 // 4)
            self._held_idx = np.concatenate(
                [rng.choice(marked, k, replace=False), rng.choice(r.held, size - k)]
            )
        return self._held_idx

    def held_out_loss(self, tracer) -> float:
        return self.loss(tracer, self.held_out_idx())
