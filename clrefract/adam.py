"""Adam over one flat parameter vector, with per-group learning rates and sparse groups.

Sparse groups (hash tables) skip entries whose gradient is exactly zero, as instant-ngp does:
their moments stay and their own step count does not advance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ParamGroup:
    name: str
    start: int
    stop: int
    lr: float
    sparse: bool = False


class Adam:
    def __init__(
        self,
        n: int,
        groups: list[ParamGroup],
        beta1: float = 0.9,
        beta2: float = 0.99,
        eps: float = 1e-15,
    ):
        self.groups, self.beta1, self.beta2, self.eps = groups, beta1, beta2, eps
        self.m = np.zeros(n)
        self.v = np.zeros(n)
        self.t = np.zeros(n, np.int64)

    def step(self, params: np.ndarray, grad: np.ndarray, lr_scale: float = 1.0) -> None:
        """Update params in place."""
        b1, b2 = self.beta1, self.beta2
        for g in self.groups:
            sl = slice(g.start, g.stop)
            gr = grad[sl]
            idx = np.flatnonzero(gr) if g.sparse else np.arange(g.stop - g.start)
            if idx.size == 0:
                continue
            gi = gr[idx]
            j = idx + g.start
            self.t[j] += 1
            self.m[j] = b1 * self.m[j] + (1 - b1) * gi
            self.v[j] = b2 * self.v[j] + (1 - b2) * gi * gi
            t = self.t[j]
            mhat = self.m[j] / (1 - b1**t)
            vhat = self.v[j] / (1 - b2**t)
            params[j] -= g.lr * lr_scale * mhat / (np.sqrt(vhat) + self.eps)

    def state(self) -> dict:
        return {"adam_m": self.m, "adam_v": self.v, "adam_t": self.t}

    def load_state(self, d: dict) -> None:
        self.m, self.v, self.t = (
            np.array(d["adam_m"], float),
            np.array(d["adam_v"], float),
            np.array(d["adam_t"], np.int64),
        )
