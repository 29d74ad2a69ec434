"""Analytic index fields and their float64 NumPy references.

Parameter layouts match kernels_cl/field_analytic.cl.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import ClrefractError
from .base import Field, smoother, smoother_d

Vec3 = tuple[float, float, float]


class AnalyticField(Field):
    source = "field_analytic.cl"
    # no kinks (every derivative continuous): the tracer builds without the steps that land
    # on them. False unless a field says so.
    smooth: bool = False

    def defines(self) -> dict:
        return {f"FIELD_{self.kind.upper().replace('-', '_')}": 1}

    def to_dict(self) -> dict:
        return {"kind": self.kind, **{k: as_plain(v) for k, v in asdict(self).items()}}

    # where params() holds centre coordinates (x, y, z): shifted with the tracer's origin
    center_slots = (0, 1, 2)

    def params_shifted(self, offset) -> np.ndarray:
        """params() for a frame whose origin is at `offset` (float64, on the host): the
        tracer works relative to the box centre so that float32 keeps its resolution far
        from the world origin."""
        p = np.array(self.params(), float)
        slots = np.asarray(self.center_slots, int)
        p[slots] -= np.resize(np.asarray(offset, float), len(slots))
        return p


def as_plain(v):
    if isinstance(v, tuple | list):
        return [as_plain(x) for x in v]
    return v


@dataclass
class Luneburg(AnalyticField):
    """eta = sqrt(2 - r^2/R^2) inside the sphere of radius R, 1 outside."""

    radius: float = 20.0
    center: Vec3 = (0.0, 0.0, 0.0)
    kind = "luneburg"

    def params(self):
        return np.array([*self.center, self.radius], float)

    @property
    def eta_max(self):
        return float(np.sqrt(2.0))

    def eval(self, pts):
        p = pts - np.asarray(self.center)
        r2 = (p * p).sum(1) / self.radius**2
        inside = r2 < 1
        eta = np.sqrt(np.where(inside, 2 - r2, 1.0))
        k = np.where(inside, -1.0 / (self.radius**2 * eta), 0.0)
        return eta, k[:, None] * p


@dataclass
class Maxwell(AnalyticField):
    """Maxwell fish-eye: eta = n0 / (1 + r^2/R^2) (never 1: use with propagate, not trace)."""

    radius: float = 20.0
    n0: float = 2.0
    center: Vec3 = (0.0, 0.0, 0.0)
    kind = "maxwell"
    smooth = True

    def params(self):
        return np.array([*self.center, self.radius, self.n0], float)

    @property
    def eta_max(self):
        return float(self.n0)

    def eval(self, pts):
        p = pts - np.asarray(self.center)
        q = 1 + (p * p).sum(1) / self.radius**2
        eta = self.n0 / q
        return eta, (-2 * eta / (q * self.radius**2))[:, None] * p


@dataclass
class Fibre(AnalyticField):
    """Parabolic (Selfoc) fibre along z: eta^2 = n0^2 (1 - a^2 rho^2)."""

    n0: float = 1.5
    a: float = 0.02
    center: tuple[float, float] = (0.0, 0.0)
    kind = "fibre"
    center_slots = (0, 1)

    def params(self):
        return np.array([*self.center, self.n0, self.a], float)

    @property
    def eta_max(self):
        return float(self.n0)

    def eval(self, pts):
        p = pts[:, :2] - np.asarray(self.center)
        q = np.maximum(1 - self.a**2 * (p * p).sum(1), 1e-12)
        eta = self.n0 * np.sqrt(q)
        k = -(self.n0**2) * self.a**2 / eta
        grad = np.zeros_like(pts)
        grad[:, :2] = k[:, None] * p
        return eta, grad


@dataclass
class Blobs(AnalyticField):
    """eta = 1 + sum_k a_k exp(-|x - c_k|^2 / 2 s_k^2): gas plumes, eta - 1 down to 1e-4."""

    centers: list = field(default_factory=lambda: [[0.0, 0.0, 0.0]])
    amplitudes: list = field(default_factory=lambda: [0.01])
    sigmas: list = field(default_factory=lambda: [10.0])
    kind = "blobs"
    smooth = True

    def __post_init__(self):
        c = np.asarray(self.centers, float).reshape(-1, 3)
        a = np.asarray(self.amplitudes, float).ravel()
        s = np.asarray(self.sigmas, float).ravel()
        if not (len(c) == len(a) == len(s)) or len(c) == 0:
            raise ClrefractError("blobs: centers, amplitudes and sigmas must have equal length")
        if np.any(s <= 0):
            raise ClrefractError("blobs: every sigma must be positive")
        self.centers, self.amplitudes, self.sigmas = c.tolist(), a.tolist(), s.tolist()

    @classmethod
    def random(
        cls,
        n: int,
        amplitude: float,
        seed: int = 0,
        extent: float = 25.0,
        sigmas: tuple[float, float] = (6.0, 12.0),
    ):
        """n blobs centred uniformly in the cube +-extent, amplitudes uniform in
        [amplitude / 2, amplitude], sigmas uniform in `sigmas`; the same for the same seed."""
        rng = np.random.default_rng(seed)
        return cls(
            centers=rng.uniform(-extent, extent, (n, 3)).tolist(),
            amplitudes=(amplitude * rng.uniform(0.5, 1.0, n)).tolist(),
            sigmas=rng.uniform(*sigmas, n).tolist(),
        )

    def defines(self):
        return {"FIELD_BLOBS": 1, "NBLOBS": len(self.amplitudes)}

    @property
    def center_slots(self):
        return tuple(6 * k + a for k in range(len(self.amplitudes)) for a in range(3))

    def params(self):
        """Per blob: centre, amplitude, -log2(e) / 2 s^2 and 1 / s^2 (the kernel's
        exponent of 2 and gradient factor, computed here in float64)."""
        c, s2 = np.asarray(self.centers), np.asarray(self.sigmas) ** 2
        q = -0.5 / np.log(2.0) / s2
        return np.column_stack([c, self.amplitudes, q, 1.0 / s2]).ravel()

    @property
    def eta_max(self):
        return 1.0 + float(np.sum(np.maximum(self.amplitudes, 0)))

    def eval(self, pts):
        eta = np.ones(len(pts))
        grad = np.zeros_like(pts)
        for c, a, s in zip(self.centers, self.amplitudes, self.sigmas):
            p = pts - np.asarray(c)
            g = a * np.exp(-0.5 * (p * p).sum(1) / s**2)
            eta += g
            grad -= (g / s**2)[:, None] * p
        return eta, grad


class SmoothSolid(AnalyticField):
    """eta = 1 + (n - 1) S(1/2 - sd/w): n inside, 1 outside, a C2 ramp of width w across
    the surface sd = 0 (sd the signed distance, negative inside)."""

    eta: float
    width: float

    def _check(self):
        if self.width <= 0:
            raise ClrefractError(f"{self.kind}: interface width must be positive")
        if self.eta < 1:
            raise ClrefractError(f"{self.kind}: eta must be at least 1")

    @property
    def eta_max(self):
        return float(self.eta)

    @property
    def suggested_step(self) -> float:
        return min(0.5, self.width / 8)

    def sdf(self, pts):
        """Signed distance (n,) and its gradient (n, 3)."""
        raise NotImplementedError

    def distance(self, pts):
        """Signed distance (n,) alone (solids whose gradient is costly skip it)."""
        return self.sdf(pts)[0]

    def eval(self, pts):
        """eta and grad eta; the gradient is computed only in the interface band, the only
        place it is non-zero."""
        pts = np.asarray(pts, float).reshape(-1, 3)
        s = 0.5 - self.distance(pts) / self.width
        dn = self.eta - 1.0
        grad = np.zeros_like(pts)
        band = (s > 0) & (s < 1)
        if band.any():
            n = self.sdf(pts[band])[1]
            grad[band] = (-dn * smoother_d(s[band]) / self.width)[:, None] * n
        return 1 + dn * smoother(s), grad


@dataclass
class Sphere(SmoothSolid):
    radius: float = 20.0
    eta: float = 1.5
    width: float = 1.0
    center: Vec3 = (0.0, 0.0, 0.0)
    kind = "sphere"

    def __post_init__(self):
        self._check()

    def params(self):
        return np.array([*self.center, self.radius, self.eta, self.width], float)

    def sdf(self, pts):
        p = pts - np.asarray(self.center)
        r = np.linalg.norm(p, axis=1)
        return r - self.radius, p / np.maximum(r, 1e-300)[:, None]


def rotation_xyz(deg: Vec3) -> np.ndarray:
    """Rotation matrix (local -> world) from successive rotations about x, y, z in degrees."""
    ax, ay, az = np.radians(deg)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


class Tilted:
    """A field in its own frame: local = M (x - center), M = rotation_xyz(tilt)^T (world to
    local); params() puts the centre in slots 0-2 and M, row-major, in slots 3-11."""

    tilt: Vec3
    center: Vec3

    @property
    def world_to_local(self):
        return rotation_xyz(self.tilt).T

    def frame_params(self) -> list:
        return [*self.center, *self.world_to_local.ravel()]

    # einsum: a (n, 3) @ (3, 3) matmul is several times slower on millions of points
    def local(self, pts):
        return np.einsum("ij,kj->ik", pts - np.asarray(self.center), self.world_to_local)

    def to_world(self, v):
        """Local vectors (n, 3) in world axes."""
        return np.einsum("ij,jk->ik", v, self.world_to_local)


_C30 = np.sqrt(3.0) / 2


@dataclass
class Prism(Tilted, SmoothSolid):
    """Equilateral triangular prism (side, length), axis along local z, rotated by `tilt`."""

    side: float = 40.0
    length: float = 40.0
    eta: float = 1.5
    width: float = 1.0
    tilt: Vec3 = (35.0, 20.0, 10.0)
    center: Vec3 = (0.0, 0.0, 0.0)
    kind = "prism"

    def __post_init__(self):
        self._check()

    def params(self):
        return np.array([*self.frame_params(), self.side, self.length, self.eta, self.width], float)

    def sdf(self, pts):
        m = self.world_to_local
        loc = self.local(pts)
        rin = self.side / (2 * np.sqrt(3))
        normals = np.array([[0, 1, 0], [-_C30, -0.5, 0], [_C30, -0.5, 0]], float)
        d = np.column_stack([loc @ normals.T - rin, np.abs(loc[:, 2]) - 0.5 * self.length])
        k = np.argmax(d, axis=1)
        n_loc = np.zeros_like(loc)
        for j in range(3):
            n_loc[k == j] = normals[j]
        cap = k == 3
        n_loc[cap] = np.column_stack(
            [np.zeros(cap.sum()), np.zeros(cap.sum()), np.sign(loc[cap, 2])]
        )
        return d[np.arange(len(d)), k], n_loc @ m

    def planes(self, centre=(0.0, 0.0, 0.0)) -> np.ndarray:
        """The five faces as rows (unit outward normal, offset from `centre`), in the world:
        the prism as a polytope (fields/interface.py's PolytopeInterface)."""
        rin = self.side / (2 * np.sqrt(3))
        local = np.array([[0, 1, 0], [-_C30, -0.5, 0], [_C30, -0.5, 0], [0, 0, 1], [0, 0, -1.0]])
        normals = local @ self.world_to_local
        offsets = np.array([rin] * 3 + [self.length / 2] * 2)
        offsets = offsets + normals @ (np.asarray(self.center, float) - np.asarray(centre, float))
        return np.column_stack([normals, offsets])


@dataclass
class Drop(SmoothSolid):
    """Water drop: revolution about z of r(t) = R sin t sin^2(t/2), z(t) = H cos t."""

    R: float = 18.0
    H: float = 22.0
    eta: float = 1.33
    width: float = 1.0
    center: Vec3 = (0.0, 0.0, 0.0)
    kind = "drop"
    samples = 24
    newton = 8
    newton_tol = 1e-9  # radians: a point whose step is smaller stops

    def __post_init__(self):
        self._check()

    def params(self):
        return np.array([*self.center, self.R, self.H, self.eta, self.width], float)

    def profile(self, t):
        return 0.5 * self.R * np.sin(t) * (1 - np.cos(t)), self.H * np.cos(t)

    def foot(self, rho, z):
        """(cos t, sin t) of the profile point nearest to (rho, z), as the kernel finds it:
        the nearest of the samples t_k, then Newton on the offset u = t - t_k kept within the
        sample interval that the descent points into (bisection where Newton would leave it:
        near the tip, where the profile's derivative vanishes, plain Newton overshoots), the
        point turned by each step with sin and cos as series."""
        hR, H = 0.5 * self.R, self.H
        n = self.samples
        dt = np.pi / n
        ts = dt * np.arange(n + 1)
        cs, ss = np.cos(ts), np.sin(ts)
        d2 = (hR * ss * (1 - cs) - rho[:, None]) ** 2 + (H * cs - z[:, None]) ** 2
        k = np.argmin(d2, axis=1)
        c, s = cs[k], ss[k]
        u = np.zeros(len(c))
        lo, hi = np.where(k > 0, -dt, 0.0), np.where(k < n, dt, 0.0)
        open_ = np.ones(len(c), bool)
        for it in range(self.newton):
            c2t = c * c - s * s
            r, zc = hR * s * (1 - c), H * c
            r1, z1 = hR * (c - c2t), -H * s
            r2, z2 = hR * (4 * s * c - s), -H * c
            g = (r - rho) * r1 + (zc - z) * z1
            dg = r1 * r1 + z1 * z1 + (r - rho) * r2 + (zc - z) * z2
            if it == 0:  # the interval the descent points into (the inner one at the ends)
                up = ((g < 0) | (k == 0)) & (k < n)
                lo, hi = np.where(up, 0.0, lo), np.where(up, hi, 0.0)
            else:
                lo, hi = np.where(g < 0, u, lo), np.where(g < 0, hi, u)
            un = u - g / np.where(dg > 0, dg, 1.0)
            bad = (dg <= 0) | ~(un >= lo) | ~(un <= hi)
            step = np.where(open_, np.where(bad, 0.5 * (lo + hi), un) - u, 0.0)
            q = step * step
            sn_ = step * (1 - q / 6 * (1 - q / 20 * (1 - q / 42)))
            cs_ = 1 - q / 2 * (1 - q / 12 * (1 - q / 30))
            cn, sn = c * cs_ - s * sn_, s * cs_ + c * sn_
            inv = 1 / np.sqrt(cn * cn + sn * sn)
            c, s, u = cn * inv, np.maximum(sn * inv, 0.0), u + step
            open_ &= np.abs(step) > self.newton_tol
            if not open_.any():
                break
        return c, s

    def sdf(self, pts):
        hR, H = 0.5 * self.R, self.H
        p = pts - np.asarray(self.center)
        rho = np.hypot(p[:, 0], p[:, 1])
        z = p[:, 2]
        c, s = self.foot(rho, z)
        er, ez = rho - hR * s * (1 - c), z - H * c
        dist = np.hypot(er, ez)
        # inside: |z| < H and rho below the profile's radius at that height (cos t = z / H)
        u = np.clip(z / H, -1, 1)
        rz = hR * np.sqrt(1 - u * u) * (1 - u)
        sgn = np.where((np.abs(z) < H) & (rho < rz), -1.0, 1.0)
        onx, onz = H * s, hR * (c - (c * c - s * s))
        on = np.maximum(np.hypot(onx, onz), 1e-300)
        far = dist > 1e-4 * (self.R + H)
        inv = 1 / np.maximum(dist, 1e-300)
        gr = np.where(far, sgn * er * inv, onx / on)
        gz = np.where(far, sgn * ez * inv, onz / on)
        irho = np.where(rho > 1e-12, 1 / np.maximum(rho, 1e-300), 0.0)
        return sgn * dist, np.column_stack([gr * p[:, 0] * irho, gr * p[:, 1] * irho, gz])


def _positive(kind: str, **values) -> None:
    for name, v in values.items():
        if not v > 0:
            raise ClrefractError(f"{kind}: {name} must be positive, got {v}")


@dataclass
class GrinRod(Tilted, AnalyticField):
    """Parabolic graded-index rod along local z: eta^2 = n0^2 (1 - a^2 rho^2) for rho < R with
    a = sqrt(1 - 1/n0^2) / R, so eta falls to exactly 1 at rho = R and stays 1 beyond; of
    length L, its ends taken to 1 over the last `cap` mm by a C2 ramp:
    eta = 1 + (eta_p(rho) - 1) S((L/2 - |z|) / cap). Within |z| < L/2 - cap it is the exact
    Selfoc profile (meridional rays rho = rho_max sin(a n0 z / beta + phase))."""

    n0: float = 1.2
    radius: float = 12.0
    length: float = 50.0
    cap: float = 8.0
    tilt: Vec3 = (0.0, 30.0, 0.0)
    center: Vec3 = (0.0, 0.0, 0.0)
    kind = "grin-rod"

    def __post_init__(self):
        _positive(self.kind, radius=self.radius, cap=self.cap, excess=self.n0 - 1)
        if not self.length > 2 * self.cap:
            raise ClrefractError(f"{self.kind}: length must exceed twice the cap length")

    @property
    def a(self) -> float:
        return float(np.sqrt(1 - 1 / self.n0**2) / self.radius)

    def params(self):
        return np.array([*self.frame_params(), self.n0, self.a, self.length / 2, self.cap], float)

    @property
    def eta_max(self):
        return float(self.n0)

    def eval(self, pts):
        loc = self.local(pts)
        q = 1 - self.a**2 * (loc[:, :2] ** 2).sum(1)
        inside = q > 1 / self.n0**2
        eta_p = self.n0 * np.sqrt(np.maximum(q, 1 / self.n0**2))
        k = np.where(inside, -(self.n0**2) * self.a**2 / eta_p, 0.0)
        u = (self.length / 2 - np.abs(loc[:, 2])) / self.cap
        w = smoother(u)
        grad = np.column_stack(
            [
                w * k * loc[:, 0],
                w * k * loc[:, 1],
                -(eta_p - 1) * np.sign(loc[:, 2]) * smoother_d(u) / self.cap,
            ]
        )
        return 1 + (eta_p - 1) * w, self.to_world(grad)


@dataclass
class GrinLens(Tilted, AnalyticField):
    """Axial graded-index disc of radius R and thickness T about local z, its index varying
    along the axis: eta = 1 + dn B(2z/T) S((R - rho) / rim), B(u) = (1 - u^2)^3 (C2, 0 at the
    faces), S the C2 smoothstep: 1 + dn on the mid-plane, 1 on the faces and past the rim."""

    dn: float = 0.4
    radius: float = 20.0
    thickness: float = 12.0
    rim: float = 4.0
    tilt: Vec3 = (40.0, 25.0, 0.0)
    center: Vec3 = (0.0, 0.0, 0.0)
    kind = "grin-lens"

    def __post_init__(self):
        _positive(self.kind, dn=self.dn, thickness=self.thickness, rim=self.rim)
        if not self.radius > self.rim:
            raise ClrefractError(f"{self.kind}: radius must exceed the rim width")

    def params(self):
        return np.array(
            [*self.frame_params(), self.dn, self.radius, self.thickness, self.rim], float
        )

    @property
    def eta_max(self):
        return 1.0 + float(self.dn)

    def eval(self, pts):
        loc = self.local(pts)
        u = 2 * loc[:, 2] / self.thickness
        t = np.maximum(1 - u * u, 0.0)
        b, db = t**3, -12 * u * t * t / self.thickness
        rho = np.hypot(loc[:, 0], loc[:, 1])
        v = (self.radius - rho) / self.rim
        w, dw = smoother(v), -smoother_d(v) / self.rim / np.maximum(rho, 1e-300)
        grad = self.dn * np.column_stack([b * dw * loc[:, 0], b * dw * loc[:, 1], db * w])
        return 1 + self.dn * b * w, self.to_world(grad)


@dataclass
class Plume(AnalyticField):
    """A buoyant plume rising along +z from its source at z0 = cz - h to z0 + 2h: a Gaussian
    cross-section widening with the height zeta = z - z0 above the source about a meandering
    axis, eta = 1 + A W exp(-r^2 / 2 s^2) with s = s0 + k zeta, A = A0 (s0 / s)^p, the axis at
    (cx + m t sin(w zeta), cy + m t sin(0.6 w zeta)), t = zeta / 2h, w = 2 pi / wavelength,
    and W = S(zeta / rise) S((2h - zeta) / fade): eta = 1 below the source and above its top."""

    amplitude: float = 1e-3
    sigma0: float = 2.0
    spread: float = 0.08
    decay: float = 5.0 / 3.0
    half_height: float = 35.0
    rise: float = 4.0
    fade: float = 15.0
    meander: float = 4.0
    wavelength: float = 40.0
    center: Vec3 = (0.0, 0.0, 5.0)
    kind = "plume"

    def __post_init__(self):
        _positive(
            self.kind,
            amplitude=self.amplitude,
            sigma0=self.sigma0,
            half_height=self.half_height,
            rise=self.rise,
            fade=self.fade,
            wavelength=self.wavelength,
        )
        if self.spread < 0 or self.decay < 0:
            raise ClrefractError(f"{self.kind}: spread and decay must not be negative")

    def params(self):
        return np.array(
            [
                *self.center,
                self.half_height,
                self.amplitude,
                self.sigma0,
                self.spread,
                self.decay,
                self.rise,
                self.fade,
                self.meander,
                2 * np.pi / self.wavelength,
            ],
            float,
        )

    @property
    def eta_max(self):
        return 1.0 + float(self.amplitude)

    def eval(self, pts):
        h2, m, w = 2 * self.half_height, self.meander, 2 * np.pi / self.wavelength
        zeta = pts[:, 2] - (self.center[2] - self.half_height)
        zc = np.clip(zeta, 0.0, h2)
        t = zc / h2
        s = self.sigma0 + self.spread * zc
        amp = self.amplitude * (self.sigma0 / s) ** self.decay
        px = pts[:, 0] - self.center[0] - m * t * np.sin(w * zc)
        py = pts[:, 1] - self.center[1] - m * t * np.sin(0.6 * w * zc)
        dxm = m * (np.sin(w * zc) / h2 + t * w * np.cos(w * zc))
        dym = m * (np.sin(0.6 * w * zc) / h2 + 0.6 * t * w * np.cos(0.6 * w * zc))
        r2 = px * px + py * py
        g = amp * np.exp(-0.5 * r2 / s**2)
        lo, hi = zeta / self.rise, (h2 - zeta) / self.fade
        win = smoother(lo) * smoother(hi)
        dwin = smoother_d(lo) * smoother(hi) / self.rise - smoother(lo) * smoother_d(hi) / self.fade
        f = g * win
        dz = (px * dxm + py * dym) / s**2 + (r2 / s**2 - self.decay) * self.spread / s
        grad = np.column_stack([-f * px / s**2, -f * py / s**2, g * dwin + f * dz])
        return 1 + f, grad


ANALYTIC = {
    c.kind: c
    for c in (Luneburg, Maxwell, Fibre, Blobs, Sphere, Prism, Drop, GrinRod, GrinLens, Plume)
}
