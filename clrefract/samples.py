"""Sample points along straight rays through the box: the segment middles that the visual
hull's tightening (clrefract.hull_tighten) and the neural baseline's compositing both use."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .fields.base import Box


@dataclass
class Samples:
    """Sample points of a batch of rays: points (P, 3), the ray of each (P,), dt per ray (n,)
    and the first sample of each ray (n + 1,: starts[r]..starts[r+1])."""

    points: np.ndarray
    ray: np.ndarray
    dt: np.ndarray
    starts: np.ndarray


def ray_samples(origins: np.ndarray, dirs: np.ndarray, box: Box, step: float) -> Samples:
    """Segment middles of rays with unit directions through the box (none for a miss)."""
    o, d = np.asarray(origins, np.float64), np.asarray(dirs, np.float64)
    t0, t1 = box.ray_span(o, d)
    t0 = np.maximum(t0, 0.0)
    hit = t1 > t0
    m = np.where(hit, np.maximum(1, np.ceil((t1 - t0) / step)), 0).astype(np.int64)
    dt = np.where(hit, (t1 - t0) / np.maximum(m, 1), 0.0)
    starts = np.concatenate([[0], np.cumsum(m)])
    ray = np.repeat(np.arange(len(o)), m)
    s = np.arange(starts[-1]) - starts[ray]
    t = t0[ray] + (s + 0.5) * dt[ray]
    return Samples(o[ray] + t[:, None] * d[ray], ray, dt, starts)
