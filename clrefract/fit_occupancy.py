"""Empty-space skipping while a field trains: which cells the fit's rays may fly through,
rebuilt from the current parameters as they move.

The rule: a cell is live (rays step in it) where eta varies now or can vary before the next
rebuild, judged from the node values that reach it (occupancy.py, no sampling):

- level set: the band |phi| < w/2 + slack, slack = 2 x occupancy_every x lr_phi (Adam moves
  a node by about its rate per step). Off the band eta is flat whatever the nodes do, so
  the gradient there is zero and skipping drops nothing. Should a node move more than the
  slack since the last rebuild, the occupancy is rebuilt at once: the bound always holds.
- voxel grid: the support of every node the fit may change (the hull's free nodes) or
  that is not 1: the others stay 1, so where only they reach, eta is flat and their
  gradient is zeroed anyway.
  Without a hull every node is free and every cell live (nothing to skip).
- hash grid: refused. A table entry changes eta wherever it is hashed to and the MLP
  everywhere: no cell is safe to skip.
"""

from __future__ import annotations

import numpy as np

from .errors import ClrefractError
from .occupancy import distance_of, live_cells_levelset, live_cells_nodes


class TrainingOccupancy:
    """Keeps a skipping tracer's occupancy ahead of the training field."""

    def __init__(self, kind: str, res: int, every: int, lr_phi: float):
        if kind == "hashgrid":
            raise ClrefractError(
                "skip_empty cannot train a hash grid: its parameters change eta anywhere "
                "(hashed table entries, the MLP); fit a voxel grid or level set, or set "
                "skip_empty = false"
            )
        if every < 1:
            raise ClrefractError(f"occupancy_every must be at least 1, got {every}")
        self.kind, self.res, self.every = kind, int(res), int(every)
        self.slack = 2.0 * every * lr_phi if kind == "levelset" else 0.0
        self.built_at: int | None = None
        self._phi0: np.ndarray | None = None
        self._tracer = None  # the tracer last given an occupancy
        self.live_fraction = 1.0
        self.rebuilds = 0

    def due(self, it: int, field) -> bool:
        if self.built_at is None or it - self.built_at >= self.every:
            return True
        if self.kind == "levelset":  # a node moved further than the slack allows
            return float(np.abs(field.phi - self._phi0).max()) > self.slack
        return False

    def live(self, field, box, free: np.ndarray | None) -> np.ndarray:
        if self.kind == "levelset":
            return live_cells_levelset(field, box, self.res, self.slack)
        if free is None:
            return np.ones((self.res,) * 3, bool)
        # nodes off 1 too: a hull filled wider than the free nodes, before the first step
        # resets them
        nodes = free.reshape(field.values.shape) | (field.values != 1.0)
        return live_cells_nodes(nodes, field, box, self.res)

    def update(self, it: int, field, tracer, free: np.ndarray | None = None, force=False):
        """Rebuild the tracer's occupancy if it is due (or forced); True if rebuilt. Level-set
        nodes as they were at the last build keep it (a start search that moves only the
        index): a rebuild would give the same."""
        if not (force or self.due(it, field)):
            return False
        if self.kind == "levelset" and tracer is self._tracer:
            if np.array_equal(field.phi, self._phi0):
                self.built_at = it
                return False
        live = self.live(field, tracer.box, free)
        tracer.set_occupancy(distance_of(live))
        self._tracer = tracer
        self.live_fraction = float(live.mean())
        self.built_at = it
        if self.kind == "levelset":
            self._phi0 = field.phi.copy()
        self.rebuilds += 1
        return True
