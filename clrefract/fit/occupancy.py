"""Empty-space skipping while a field trains: which cells the fit's rays may fly through,
rebuilt from the current parameters as they move.

A cell is live (rays step in it) where eta varies now or can vary before the next rebuild,
judged from the node values that reach it (occupancy.py, no sampling); the field kind's
adapter says how (kinds.py):

- level set: the band |phi| < w/2 + slack, slack = 2 x occupancy_every x lr_phi (Adam moves
  a node by about its rate per step). Off the band eta is flat whatever the nodes do, so
  the gradient there is zero and skipping drops nothing. Should a node move more than the
  slack since the last rebuild, the occupancy is rebuilt at once: the bound always holds.
- voxel grid: the support of every node the fit may change (the hull's free nodes) or
  that is not 1: the others stay 1, so where only they reach, eta is flat and their
  gradient is zeroed anyway. Without a hull every node is free and every cell live.
- hash grid: refused. A table entry changes eta wherever it is hashed to and the MLP
  everywhere: no cell is safe to skip.
"""

from __future__ import annotations

import numpy as np

from ..occupancy import distance_of


class TrainingOccupancy:
    """Keeps a skipping tracer's occupancy ahead of the training field (of `kind`, an
    adapter of kinds.py)."""

    def __init__(self, kind, res: int, every: int, lr_phi: float):
        self.kind, self.res, self.every = kind, int(res), int(every)
        self.slack = kind.occupancy_slack(every, lr_phi)
        self.built_at: int | None = None
        self._built_from = None  # the parameters' state at the last build (kind's snapshot)
        self._tracer = None  # the tracer last given an occupancy
        self.live_fraction = 1.0
        self.rebuilds = 0

    def due(self, it: int, field) -> bool:
        if self.built_at is None or it - self.built_at >= self.every:
            return True
        return self.kind.moved_past(field, self._built_from, self.slack)

    def update(self, it: int, field, tracer, free: np.ndarray | None = None, force=False):
        """Rebuild the tracer's occupancy if it is due (or forced); True if rebuilt. A field
        as it was at the last build keeps it (a start search that moves only a level set's
        index): a rebuild would give the same."""
        if not (force or self.due(it, field)):
            return False
        if tracer is self._tracer and self.kind.unchanged(field, self._built_from):
            self.built_at = it
            return False
        live = self.kind.live_cells(field, tracer.box, self.res, self.slack, free)
        tracer.set_occupancy(distance_of(live))
        self._tracer = tracer
        self.live_fraction = float(live.mean())
        self.built_at = it
        self._built_from = self.kind.snapshot(field)
        self.rebuilds += 1
        return True
