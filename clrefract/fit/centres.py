"""Camera centres fitted with the field (`camera_centres = "fitted"`): each training view's
centre moves in its image plane on the loss's gradient with respect to its rays' origins (the
adjoint carried back to each ray's start, summed over the view's rays).

A view's gradient is that of the hundred or so rays a batch draws from it: mostly noise where
the object hardly moves with the camera (a drop of water refracts little). Adam moves every
parameter at its rate whatever its noise, and such centres walked off (a realistic drop's
fitted centres ended 0.30 mm off where the recorded ones were 0.16 mm off). So a centre moves
by a fixed length a step only where its running mean gradient stands out of its noise: a
t-statistic over the last 1 / (1 - BETA) steps above T_MOVE starts it, and at 2 T_MOVE it
takes the whole step. Near its optimum the gradient's sign wanders, and the centre stops.

Only the object places a camera: the panorama is at infinity. A shift common to every camera
is a shift of the object, which the field makes as well, so the common part (the least-squares
translation of all the views' shifts) is taken out after each step: the recorded centres hold
on average. Along its axis a camera moves the object's scale by the shift over the distance, a
part of a pixel that the images hardly see (camera_positions.py), so that axis stays.
Held-out views keep their recorded centres: their losses judge the field.

The gate stops a centre where its gradient sinks into its noise, a tenth of a pixel or so
from its optimum on noisy photographs. So at SOLVES_AT of the run every view's centre is also
solved against the field as it stands, with all of the view's pixels near the object
(view_offsets.py's least squares), and the field goes on from the solved centres.
"""

from __future__ import annotations

import numpy as np

KEY = "centres_"  # checkpoint.npz keys
BETA = 0.98  # the gradient's running moments weigh about the last 1 / (1 - BETA) steps
T_MOVE = 3.0  # t-statistic of a view's mean gradient at which its centre starts to move
MIN_SEEN = 8  # steps' worth of gradients before any centre moves (a spread to test against)
SOLVES_AT = (0.25, 0.5)  # shares of the run after which every centre is solved outright


def centres_setting(cfg, scene, registered: bool) -> str:
    """`camera_centres` as a run goes with it: "auto" is "fitted" for a real capture, one
    whose background the fit registered or that `dataset import` made, else "recorded"."""
    if cfg.camera_centres in ("fitted", "recorded"):
        return cfg.camera_centres
    return "fitted" if registered or "import" in scene.extra else "recorded"


class CameraCentres:
    """Offsets (mm) of the training views' centres, along each view's right and up axes.
    footprint: a pixel's width at the object (mm), the unit of the rate `lr` (pixels a step):
    what the images see of a camera's move."""

    def __init__(
        self, cameras, view_of: np.ndarray, held: np.ndarray, footprint: float, lr: float,
        decay=None,
    ):  # fmt: skip
        self.basis = np.stack([np.stack([c.c2w[:3, 0], c.c2w[:3, 1]], 1) for c in cameras])
        self.view_of = view_of
        self.frozen = np.zeros(len(cameras), bool)
        self.frozen[np.unique(view_of[held])] = True
        self.uv = np.zeros((len(cameras), 2))
        self.footprint = footprint
        self.lr = lr * footprint  # mm a step
        self.decay = decay or (lambda it: 1.0)  # the rate's scale at an iteration
        self.m = np.zeros_like(self.uv)  # running mean of each view's gradient
        self.v = np.zeros_like(self.uv)  # and of its square
        self.t = 0  # steps taken

    def world(self) -> np.ndarray:
        """Each view's offset in world coordinates, (views, 3)."""
        return np.einsum("vkj,vj->vk", self.basis, self.uv)

    def offsets(self, rays: np.ndarray) -> np.ndarray:
        """The origin shift of each of `rays` (indices over the views' pixels), (n, 3)."""
        return self.world()[self.view_of[rays]]

    def step(self, rays: np.ndarray, origin_grad: np.ndarray, it: int) -> None:
        """One step of the offsets on dJ/d(origin) of `rays`, then the common translation
        taken out."""
        per_view = np.zeros((len(self.uv), 3))
        np.add.at(per_view, self.view_of[rays], origin_grad)
        grad = np.einsum("vkj,vk->vj", self.basis, per_view)
        self.t += 1
        self.m = BETA * self.m + (1 - BETA) * grad
        self.v = BETA * self.v + (1 - BETA) * grad * grad
        self.uv -= self.lr * self.decay(it) * self.moves()
        self._remove_common()

    def solve_due(self, it: int, iterations: int) -> bool:
        """Whether the centres are solved outright after step `it` of `iterations`."""
        return it in {max(round(share * iterations), 1) for share in SOLVES_AT}

    def moving(self) -> np.ndarray:
        """The indices of the views whose centres move (not held out)."""
        return np.flatnonzero(~self.frozen)

    def take_solved(self, views: np.ndarray, right_up: np.ndarray) -> None:
        """Move `views` by `right_up` (mm along their right and up axes, from where they
        are), the common translation taken out; the gradients' moments start again, as
        they were of the old centres."""
        self.uv[views] += right_up
        self._remove_common()
        self.m[:] = 0.0
        self.v[:] = 0.0
        self.t = 0

    def moves(self) -> np.ndarray:
        """Each offset's step, a share of the rate towards its lower loss: 0 until its mean
        gradient stands T_MOVE standard errors out of its noise, 1 from twice that."""
        w = 1 - BETA**self.t  # the moments' bias, and their weights' effective count
        n_eff = w * w * (1 + BETA) / ((1 - BETA) * (1 - BETA ** (2 * self.t)))
        if n_eff < MIN_SEEN:
            return np.zeros_like(self.uv)
        mean, sq = self.m / w, self.v / w
        spread = np.sqrt(np.maximum(sq - mean * mean, 0.0) * n_eff / (n_eff - 1))
        z = np.abs(mean) * np.sqrt(n_eff) / np.maximum(spread, 1e-300)
        share = np.clip(z / T_MOVE - 1, 0.0, 1.0)
        share[self.frozen] = 0.0
        return np.sign(mean) * share

    def _remove_common(self) -> None:
        moving = ~self.frozen
        b = self.basis[moving]
        normal = np.einsum("vkj,vlj->kl", b, b)
        if np.linalg.matrix_rank(normal) < 3:  # views from one side: no translation to fix
            return
        t = np.linalg.solve(normal, np.einsum("vkj,vj->k", b, self.uv[moving]))
        self.uv[moving] -= np.einsum("vkj,k->vj", b, t)

    # --- the run folder -----------------------------------------------------------------------
    def state(self) -> dict:
        return {KEY + "uv": self.uv, KEY + "m": self.m, KEY + "v": self.v, KEY + "t": self.t}

    def restore(self, saved: dict) -> None:
        if KEY + "uv" not in saved:
            return  # a run that fitted none yet
        self.uv = np.array(saved[KEY + "uv"], float).reshape(self.uv.shape)
        self.m = np.array(saved[KEY + "m"], float).reshape(self.uv.shape)
        self.v = np.array(saved[KEY + "v"], float).reshape(self.uv.shape)
        self.t = int(saved[KEY + "t"])

    def report(self, frames: list[tuple[str, str]]) -> dict:
        """What camera_centres.json holds: each training view's offset (`frames`: its
        "file: frames[k]" name and image path) and their spread in pixels at the object."""
        world = self.world()
        views = [
            {
                "frame": name,
                "file_path": path,
                "offset_mm": [round(float(x), 4) for x in world[v]],
                "right_up_mm": [round(float(x), 4) for x in self.uv[v]],
                "shift_px": round(float(np.linalg.norm(self.uv[v])) / self.footprint, 3),
            }
            for v, (name, path) in enumerate(frames)
            if not self.frozen[v]
        ]
        moved = np.linalg.norm(self.uv[~self.frozen], axis=1)
        return {
            "views": views,
            "rms_offset_mm": round(float(np.sqrt(np.mean(moved**2))) if moved.size else 0.0, 4),
            "footprint_mm": round(self.footprint, 4),
            "held_out_views": "keep their recorded centres",
        }
