"""Voxel-grid index field: res^3 node values over the box (the paper's grid baseline).

eta = 1 + W(x) (g(x) - 1), g the trilinear or smoothstep-weighted (C1) interpolant of the
node values and W the box window. The adjoint pass needs second derivatives of eta: with
trilinear weights they are Dirac masses on the cell faces that a pointwise adjoint misses,
so fitting uses smoothstep weights.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.ndimage import map_coordinates

from ..adam import ParamGroup
from ..errors import ClrefractError
from .base import Box, Field, box_window

INTERPS = ("trilinear", "smoothstep")


class VoxelGrid(Field):
    kind = "voxel"
    source = "field_voxel.cl"
    adjoint_source = "voxel_adjoint.cl"

    def __init__(self, values: np.ndarray, box: Box | None = None, interp: str = "smoothstep",
                 eta_max: float | None = None):
        values = np.array(values, dtype=np.float64)
        if values.ndim != 3 or min(values.shape) < 2:
            raise ClrefractError(f"voxel grid needs a 3-D array of at least 2^3, got "
                                 f"{values.shape}")
        if interp not in INTERPS:
            raise ClrefractError(f"voxel interp must be one of {INTERPS}, got {interp!r}")
        self.values, self.box, self.interp = values, box or Box(), interp
        self._eta_max = eta_max

    # --- Field ---------------------------------------------------------------------------
    def defines(self):
        nx, ny, nz = self.values.shape
        return {"FIELD_VOXEL": 1, "VOX_NX": nx, "VOX_NY": ny, "VOX_NZ": nz,
                "VOX_SMOOTH": int(self.interp == "smoothstep")}

    def params(self):
        return np.zeros(1)

    def data(self):
        return self.values.ravel()

    def set_data(self, params: np.ndarray) -> None:
        self.values = np.asarray(params, np.float64).reshape(self.values.shape).copy()

    def uses_window(self) -> bool:
        return True

    @property
    def eta_max(self) -> float:
        return float(self._eta_max or self.values.max())

    @property
    def spacing(self) -> np.ndarray:
        return self.box.size / (np.array(self.values.shape) - 1)

    @property
    def suggested_step(self) -> float:
        return float(min(0.5, self.spacing.min() / 2))

    def to_dict(self) -> dict:
        return {"kind": "voxel", "shape": list(self.values.shape), "interp": self.interp,
                "box": self.box.to_dict()}

    def eval(self, pts):
        pts = np.asarray(pts, np.float64)
        n = np.array(self.values.shape)
        u = np.clip((pts - np.asarray(self.box.lo)) / self.spacing, 0, n - 1)
        i = np.minimum(np.floor(u).astype(int), n - 2)
        t = u - i
        if self.interp == "smoothstep":
            s, ds = t * t * (3 - 2 * t), 6 * t * (1 - t)
        else:
            s, ds = t, np.ones_like(t)
        ds = ds / self.spacing
        g = np.zeros(len(pts))
        gg = np.zeros((len(pts), 3))
        for a in (0, 1):
            wx, dx = (s[:, 0], ds[:, 0]) if a else (1 - s[:, 0], -ds[:, 0])
            for b in (0, 1):
                wy, dy = (s[:, 1], ds[:, 1]) if b else (1 - s[:, 1], -ds[:, 1])
                for c in (0, 1):
                    wz, dz = (s[:, 2], ds[:, 2]) if c else (1 - s[:, 2], -ds[:, 2])
                    th = self.values[i[:, 0] + a, i[:, 1] + b, i[:, 2] + c]
                    g += wx * wy * wz * th
                    gg += np.column_stack([dx * wy * wz, wx * dy * wz, wx * wy * dz]) * th[:, None]
        w, gw = box_window(self.box, pts)
        return 1 + w * (g - 1), gw * (g - 1)[:, None] + w[:, None] * gg

    # --- fitting -------------------------------------------------------------------------
    def param_groups(self, lr: float, **_) -> list[ParamGroup]:
        return [ParamGroup("voxels", 0, self.values.size, lr)]

    def regularizer(self, params: np.ndarray) -> tuple[float, np.ndarray]:
        """Mean squared difference of neighbouring nodes (a discrete |grad eta|^2)."""
        v = np.asarray(params).reshape(self.values.shape)
        grad = np.zeros_like(v)
        total, count = 0.0, 0
        for ax in range(3):
            d = np.diff(v, axis=ax)
            total += float((d * d).sum())
            count += d.size
            sl_hi = [slice(None)] * 3
            sl_lo = [slice(None)] * 3
            sl_hi[ax], sl_lo[ax] = slice(1, None), slice(None, -1)
            grad[tuple(sl_hi)] += 2 * d
            grad[tuple(sl_lo)] -= 2 * d
        return total / count, grad.ravel() / count

    def resampled_values(self, arr: np.ndarray, res: int) -> np.ndarray:
        """A node array of this grid's shape resampled (trilinearly) to res^3 nodes."""
        n = np.array(arr.shape)
        coords = np.stack(np.meshgrid(*[np.linspace(0, n[k] - 1, res) for k in range(3)],
                                      indexing="ij"))
        return map_coordinates(arr, coords, order=1, mode="nearest")

    def resampled(self, res: int) -> VoxelGrid:
        return VoxelGrid(self.resampled_values(self.values, res), self.box, self.interp,
                         self._eta_max)

    @classmethod
    def from_field(cls, field: Field, box: Box, res: int, interp: str = "smoothstep"):
        ax = [np.linspace(box.lo[k], box.hi[k], res) for k in range(3)]
        pts = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
        vals = np.concatenate([field.eval(pts[s : s + (1 << 18)])[0]
                               for s in range(0, len(pts), 1 << 18)])
        return cls(vals.reshape(res, res, res), box, interp)

    # --- files ---------------------------------------------------------------------------
    def save(self, path) -> None:
        from ..imageio import atomic_path

        with atomic_path(path, suffix=".npz") as tmp:
            np.savez_compressed(tmp, kind="voxel", values=self.values.astype(np.float32),
                                lo=self.box.lo, hi=self.box.hi, margin=self.box.margin,
                                interp=self.interp)

    @classmethod
    def load(cls, path) -> VoxelGrid:
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                values = np.asarray(z["values"], np.float64)
                box = Box(tuple(z["lo"]), tuple(z["hi"]), float(z["margin"]))
                interp = str(z["interp"]) if "interp" in z else "smoothstep"
        except FileNotFoundError:
            raise ClrefractError(f"{path}: voxel grid file not found") from None
        except (KeyError, ValueError, OSError) as exc:
            raise ClrefractError(f"{path}: not a voxel grid file ({exc})") from None
        if values.ndim != 3:
            raise ClrefractError(f"{path}: values must be a 3-D array, got {values.shape}")
        if not np.all(np.isfinite(values)):
            raise ClrefractError(f"{path}: values contain NaN or infinity")
        if values.min() < 1.0 - 1e-6:
            raise ClrefractError(f"{path}: eta below 1 ({values.min():.4g}) is not physical")
        return cls(values, box, interp)
