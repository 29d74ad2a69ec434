"""How fine a field the photographs can resolve: the size of a pixel at the object.

A surface detail smaller than the pixel footprint at the object falls inside one pixel, so
grid cells (or a hash grid's finest cells) finer than it cost work without changing any
image. On the quick protocol (128 x 128, cameras 200 mm away, focal 239 px) the footprint is
0.84 mm, which is the cell size the fits' measured defaults use (64 cells over a 55-65 mm
object box).
"""

from __future__ import annotations

import math

import numpy as np

from .errors import ClrefractError

MIN_CELLS, MAX_CELLS = 16, 256


def pixel_footprint_mm(cameras, center) -> float:
    """Median over the views of the width of one pixel at `center`: distance / focal (px)."""
    c = np.asarray(center, float)
    sizes = [float(np.linalg.norm(cam.position - c)) / float(cam.fl_x) for cam in cameras]
    if not sizes or not all(math.isfinite(s) and s > 0 for s in sizes):
        raise ClrefractError("cannot size the field from the photographs: no usable camera")
    return float(np.median(sizes))


def cells_for(size_mm: float, footprint_mm: float) -> int:
    """Cells across `size_mm` at one per footprint, within [MIN_CELLS, MAX_CELLS]."""
    return int(np.clip(math.ceil(size_mm / footprint_mm), MIN_CELLS, MAX_CELLS))
