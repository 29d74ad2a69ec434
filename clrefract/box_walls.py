"""Whether the medium runs on to the box's walls, seen in the refraction masks alone, and a
box that would hold it.

A fitted field is 1 within a margin of the box's walls and free only beyond two margins
(fields.base.box_window): a plume or a blob cluster that the box cuts is forced to air there
and fits badly. No index is known before a fit, but the masks show where the medium bends
rays: their visual hull, carved in the box grown to twice its size about its centre, comes
near a wall, or runs past it, where the medium does.

The masks mark only where rays bend enough to change a pixel's colour, so a graded medium
runs on beyond its hull: a Gaussian blob (index 1.05, sigma 8 mm) marks masks out to about
2 sigma from its centre, and its index falls to 1e-3 of its peak at 3.7 sigma. Hence a hull
within three margins of a wall reaches it (two where the fit holds eta near 1, one for the
unmarked rim), and the box suggested moves that wall out by half the hull's extent across it
beyond the hull, plus two margins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .fields.base import Box
from .hull import CARVE_MAX, TOLERANCE, visual_hull

GROWTH = 2.0  # the hull is carved in the box scaled by this about its centre
RES = 32  # nodes across that box along each axis (a cell of 6.5 mm for a 100 mm box)
MAX_VIEWS = 40  # views carved at most, evenly spread (the hull of 80 views takes 1 s)
REACH_MARGINS = 3.0  # a hull this many box margins or less from a wall reaches it
AXES = "xyz"


@dataclass
class Walls:
    """Walls of a box that the masks' hull reaches, and a box that would hold the hull."""

    box: Box  # the box checked
    sides: tuple[str, ...]  # walls reached: "+z", "-x", ...
    hull_lo: tuple[float, float, float]  # the hull's extent (mm)
    hull_hi: tuple[float, float, float]
    suggested: Box
    at_least: bool  # the hull ran on to the edge of the region carved

    def box_option(self) -> str:
        """The suggested box as `--box` takes it."""
        return "--box " + ",".join(_num(v) for v in (*self.suggested.lo, *self.suggested.hi))

    def message(self) -> str:
        """One line: the walls reached, how far the hull runs, and the --box to give instead."""
        walls, reach = [], []
        for side in self.sides:
            a = AXES.index(side[1])
            up = side[0] == "+"
            walls.append(f"{side[1]} = {_num((self.box.hi if up else self.box.lo)[a])}")
            reach.append(f"{side[1]} = {_num((self.hull_hi if up else self.hull_lo)[a])}")
        return (
            f"the medium reaches the box's {', '.join(self.sides)} "
            f"wall{'s' * (len(self.sides) > 1)} ({', '.join(walls)}): the refraction masks' "
            f"hull runs to {', '.join(reach)} mm, and the fit holds eta near 1 within "
            f"{_num(2 * self.box.margin)} mm of a wall (a graded medium runs on past its "
            f"masks); grow the box{' at least' * self.at_least} to {self.box_option()}"
        )

    def to_dict(self) -> dict:
        return {
            "sides": list(self.sides),
            "hull_lo": list(self.hull_lo),
            "hull_hi": list(self.hull_hi),
            "suggested_box": self.suggested.to_dict(),
            "at_least": self.at_least,
        }


def _num(v: float) -> str:
    return f"{round(float(v), 1):.5g}"


def pick_views(n: int) -> list[int]:
    """The views carved of n: all, or MAX_VIEWS of them evenly spread."""
    if n <= MAX_VIEWS:
        return list(range(n))
    return sorted({int(round(v)) for v in np.linspace(0, n - 1, MAX_VIEWS)})


def _round_out(v: float, step: float, up: bool) -> float:
    return float((np.ceil if up else np.floor)(v / step - 1e-9) * step)


def box_walls(
    box: Box,
    cameras: list,
    masks: list[np.ndarray],
    tolerance: float = TOLERANCE,
    carve: float = CARVE_MAX,
) -> Walls | None:
    """The walls of `box` that the masks' visual hull (by the fit's hull rule: `tolerance`,
    `carve`) comes within REACH_MARGINS margins of, with a box that would hold it; None where
    it reaches none, or where the masks agree on no hull (a faint medium)."""
    take = pick_views(len(cameras))
    lo, hi = np.asarray(box.lo, float), np.asarray(box.hi, float)
    centre, half = (lo + hi) / 2, GROWTH * (hi - lo) / 2
    region = Box(tuple(centre - half), tuple(centre + half), box.margin)
    hull = visual_hull(
        region, [cameras[v] for v in take], [masks[v] for v in take], RES, 0.0, tolerance, carve
    )
    if not hull.found:
        return None
    axes = [np.linspace(region.lo[a], region.hi[a], RES) for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    d = hull.distance.ravel()
    inside = d > 0
    # a node d mm inside holds a ball of radius d: the hull runs at least d beyond it
    h_lo = (pts[inside] - d[inside, None]).min(axis=0)
    h_hi = (pts[inside] + d[inside, None]).max(axis=0)
    near = REACH_MARGINS * box.margin
    sides, new_lo, new_hi = [], lo.copy(), hi.copy()
    # the box suggested is rounded out to 1 mm for a box 32 to 316 mm across (0.1 mm below)
    step = 10.0 ** np.round(np.log10(float(np.max(hi - lo))) - 2)
    for a in range(3):
        pad = box.margin * 2 + max((h_hi[a] - h_lo[a]) / 2, box.margin)
        if h_lo[a] < lo[a] + near:
            sides.append(f"-{AXES[a]}")
            new_lo[a] = min(lo[a], _round_out(h_lo[a] - pad, step, up=False))
        if h_hi[a] > hi[a] - near:
            sides.append(f"+{AXES[a]}")
            new_hi[a] = max(hi[a], _round_out(h_hi[a] + pad, step, up=True))
    if not sides:
        return None
    edge = 2 * region.margin + float(np.max(region.size)) / (RES - 1)  # a cell from its wall
    at_least = bool(
        np.any(h_lo < np.asarray(region.lo) + edge) or np.any(h_hi > np.asarray(region.hi) - edge)
    )
    suggested = Box(tuple(new_lo.tolist()), tuple(new_hi.tolist()), box.margin)
    return Walls(box, tuple(sides), tuple(h_lo.tolist()), tuple(h_hi.tolist()), suggested, at_least)
