"""A family of glass solids beyond the paper's three (issue 15), as signed-distance functions.

Each shape is a SmoothSolid: index `eta` inside, 1 outside, smoothed over `width` only for the
ground-truth eta volume. Its surface is the zero set of a signed distance (negative inside) in
the shape's local frame, local = M (x - center) with M = rotation_xyz(tilt)^T. The images are
rendered by exact Snell refraction at that sharp zero set (clrefract.snell_sdf); the OpenCL
kernel kernels_cl/snell_sdf.cl carries the same SDFs in C, so keep the two in step (the tests
compare them ray by ray).

Sphere tracing is only safe on a Lipschitz function: every SDF here is 1-Lipschitz (exact
distances, a min of exact distances, a smooth union of exact distances), except the vase,
whose normalised implicit function has a computed bound `lipschitz` the tracer divides by.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import ClrefractError
from .fields.analytic import SmoothSolid, Vec3, as_plain, rotation_xyz

ETA_RANGE = (1.2, 1.9)
LIMIT = 40.0  # every family object lies inside [-LIMIT, LIMIT]^3
GRAD_REL = 1e-6  # central-difference step of normals, times the bounding radius (as the kernel)


def central_grad(fn, pts: np.ndarray, h: float) -> np.ndarray:
    g = np.empty_like(pts)
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        g[:, j] = (fn(pts + e) - fn(pts - e)) / (2 * h)
    return g


def _finite_vec3(v, what: str, kind: str) -> tuple[float, float, float]:
    try:
        a = np.asarray(v, float).ravel()
    except (TypeError, ValueError):
        a = np.empty(0)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ClrefractError(f"{kind}: {what} must be three finite numbers, got {v!r}")
    return tuple(float(x) for x in a)


def corner_radius(faces: np.ndarray) -> float:
    """The largest distance from the origin of a corner of the solid n . p <= d (rows (n, d)
    of `faces`; inf where they close no solid about the origin)."""
    from scipy.spatial import HalfspaceIntersection

    try:
        hs = HalfspaceIntersection(np.column_stack([faces[:, :3], -faces[:, 3]]), np.zeros(3))
    except Exception:  # noqa: BLE001 - an unbounded or degenerate intersection
        return math.inf
    pts = hs.intersections
    return float(np.linalg.norm(pts, axis=1).max()) if np.all(np.isfinite(pts)) else math.inf


def _check_seed(kind: str, seed) -> None:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer):
        raise ClrefractError(f"{kind}: seed must be an integer, got {seed!r}")
    if seed < 0:
        raise ClrefractError(f"{kind}: seed must be >= 0, got {seed}")


def _smin(a, b, k):
    """Polynomial smooth minimum: its gradient is a convex combination of the two gradients,
    so a smooth union of 1-Lipschitz functions stays 1-Lipschitz."""
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - 0.25 * k * h * h


def _rounded_box(p, b, r):
    q = np.abs(p) - b
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0) - r


@dataclass
class SdfSolid(SmoothSolid):
    """Base of the family: a glass solid bounded by the zero set of a signed distance."""

    eta: float = 1.5
    width: float = 0.8
    tilt: Vec3 = (0.0, 0.0, 0.0)
    center: Vec3 = (0.0, 0.0, 0.0)
    kind = "sdf"
    lipschitz = 1.0

    def __post_init__(self):
        k = self.kind
        try:
            eta = float(self.eta)
        except (TypeError, ValueError):
            eta = math.nan
        if not ETA_RANGE[0] <= eta <= ETA_RANGE[1]:
            raise ClrefractError(
                f"{k}: eta must be between {ETA_RANGE[0]} and {ETA_RANGE[1]}, got {self.eta!r}"
            )
        self.eta = eta
        if not (isinstance(self.width, int | float) and self.width > 0):
            raise ClrefractError(f"{k}: interface width must be positive, got {self.width!r}")
        self.width = float(self.width)
        self.tilt = _finite_vec3(self.tilt, "tilt (degrees)", k)
        self.center = _finite_vec3(self.center, "center", k)
        self._check_params()
        reach = max(abs(c) for c in self.center) + self.bounding_radius
        if reach > LIMIT:
            raise ClrefractError(
                f"{k}: the object reaches {reach:.1f} mm from the origin; it must fit in "
                f"[-{LIMIT:g}, {LIMIT:g}]^3 (smaller parameters or a centre nearer 0)"
            )

    # --- what each shape defines ----------------------------------------------------------
    def _check_params(self) -> None:
        pass

    def local_distance(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (n,) at local points p (n, 3), negative inside."""
        raise NotImplementedError

    @property
    def bounding_radius(self) -> float:
        """Radius of a sphere about `center` holding the whole solid."""
        raise NotImplementedError

    def shape_params(self) -> list[float]:
        """The shape's own parameters for kernels_cl/snell_sdf.cl (from sp[15] on)."""
        raise NotImplementedError

    # --- common ----------------------------------------------------------------------------
    @property
    def world_to_local(self) -> np.ndarray:
        return rotation_xyz(self.tilt).T

    def to_local(self, pts) -> np.ndarray:
        return (np.asarray(pts, float).reshape(-1, 3) - np.asarray(self.center)) @ (
            self.world_to_local.T
        )

    def distance(self, pts) -> np.ndarray:
        """Signed distance (n,) at world points (n, 3)."""
        return self.local_distance(self.to_local(pts))

    def inside(self, pts) -> np.ndarray:
        return self.distance(pts) < 0

    @property
    def grad_step(self) -> float:
        return GRAD_REL * self.bounding_radius

    def sdf(self, pts):
        """Signed distance and its gradient (central differences), as SmoothSolid wants."""
        pts = np.asarray(pts, float).reshape(-1, 3)
        return self.distance(pts), central_grad(self.distance, pts, self.grad_step)

    def params(self):
        raise ClrefractError(
            f"{self.kind}: no eikonal kernel for this shape; it is rendered by exact Snell "
            "refraction (clrefract.snell_sdf) and fitted from its dataset"
        )

    def to_dict(self) -> dict:
        from dataclasses import asdict

        return {"kind": self.kind, **{k: as_plain(v) for k, v in asdict(self).items()}}

    def kernel_defines(self) -> dict:
        return {f"SHAPE_{self.kind.upper().replace('-', '_')}": 1}

    def kernel_params(self) -> np.ndarray:
        """sp of kernels_cl/snell_sdf.cl: centre, M (row-major), eta, L, Rb, shape params."""
        return np.array(
            [
                *self.center,
                *self.world_to_local.ravel(),
                self.eta,
                self.lipschitz,
                self.bounding_radius,
                *self.shape_params(),
            ],
            float,
        )

    def mesh(self, spacing: float = 0.3, project: int = 2):
        """Ground-truth surface: marching cubes of the SDF on a grid of `spacing` mm around
        the solid, then `project` Newton steps of every vertex onto the zero set (removes the
        marching-cubes chord error). Returns world vertices (n, 3) and faces (m, 3)."""
        from skimage.measure import marching_cubes

        r = self.bounding_radius + 2 * spacing
        n = int(math.ceil(2 * r / spacing)) + 1
        ax = np.linspace(-r, r, n)
        vol = np.empty((n, n, n))
        yy, zz = np.meshgrid(ax, ax, indexing="ij")
        for i, x in enumerate(ax):  # slab by slab: a few MB at a time
            pts = np.column_stack([np.full(yy.size, x), yy.ravel(), zz.ravel()])
            vol[i] = self.local_distance(pts).reshape(n, n)
        h = float(ax[1] - ax[0])
        verts, faces, _, _ = marching_cubes(vol, 0.0, spacing=(h, h, h))
        v = verts - r
        for _ in range(project):
            f = self.local_distance(v)
            g = central_grad(self.local_distance, v, 1e-5 * self.bounding_radius)
            v = v - (f / np.maximum((g * g).sum(1), 1e-12))[:, None] * g
        return v @ self.world_to_local + np.asarray(self.center), faces.astype(np.int64)


@dataclass
class SdfSphere(SdfSolid):
    """A ball as an SDF: checks the SDF renderer against the analytic sphere (not a CLI shape)."""

    radius: float = 20.0
    kind = "sdf-sphere"

    def _check_params(self):
        if not self.radius > 0:
            raise ClrefractError(f"{self.kind}: radius must be positive, got {self.radius}")

    def local_distance(self, p):
        return np.linalg.norm(p, axis=-1) - self.radius

    @property
    def bounding_radius(self):
        return float(self.radius)

    def shape_params(self):
        return [self.radius]


@dataclass
class RoundedCube(SdfSolid):
    """Cube of edge `size` with edges and corners rounded by `rounding` (exact SDF)."""

    size: float = 30.0
    rounding: float = 3.0
    tilt: Vec3 = (25.0, 35.0, 10.0)
    kind = "rounded-cube"

    def _check_params(self):
        if not (self.size > 0 and 0 <= self.rounding < self.size / 2):
            raise ClrefractError(
                f"{self.kind}: need size > 0 and 0 <= rounding < size/2, got "
                f"size={self.size}, rounding={self.rounding}"
            )

    def local_distance(self, p):
        return _rounded_box(p, 0.5 * self.size - self.rounding, self.rounding)

    @property
    def bounding_radius(self):
        return math.sqrt(3.0) * (0.5 * self.size - self.rounding) + self.rounding

    def shape_params(self):
        return [0.5 * self.size - self.rounding, self.rounding]


@dataclass
class Cylinder(SdfSolid):
    """Capped cylinder about local z, its rims rounded by `rounding` (0: sharp; exact SDF)."""

    radius: float = 14.0
    height: float = 32.0
    rounding: float = 2.0
    tilt: Vec3 = (30.0, 15.0, 0.0)
    kind = "cylinder"

    def _check_params(self):
        if not (
            self.radius > 0
            and self.height > 0
            and 0 <= self.rounding < min(self.radius, self.height / 2)
        ):
            raise ClrefractError(
                f"{self.kind}: need radius, height > 0 and 0 <= rounding < min(radius, "
                f"height/2), got {self.radius}, {self.height}, {self.rounding}"
            )

    def local_distance(self, p):
        dr = np.hypot(p[:, 0], p[:, 1]) - (self.radius - self.rounding)
        dz = np.abs(p[:, 2]) - (0.5 * self.height - self.rounding)
        return (
            np.minimum(np.maximum(dr, dz), 0.0)
            + np.hypot(np.maximum(dr, 0.0), np.maximum(dz, 0.0))
            - self.rounding
        )

    @property
    def bounding_radius(self):
        return math.hypot(self.radius, 0.5 * self.height)

    def shape_params(self):
        return [self.radius - self.rounding, 0.5 * self.height - self.rounding, self.rounding]


@dataclass
class Bowl(SdfSolid):
    """Thick spherical shell (mid-wall radius `radius`, wall `thickness`) cut open by the
    plane z = `cut` (local), with rounded rims: an exact SDF (the cut hollow sphere)."""

    radius: float = 18.0
    thickness: float = 5.0
    cut: float = 8.0
    tilt: Vec3 = (40.0, 0.0, 25.0)
    kind = "bowl"

    def _check_params(self):
        if not (0 < self.thickness < self.radius and abs(self.cut) < self.radius):
            raise ClrefractError(
                f"{self.kind}: need 0 < thickness < radius and |cut| < radius, got "
                f"radius={self.radius}, thickness={self.thickness}, cut={self.cut}"
            )

    def _rim(self):
        return math.sqrt(self.radius**2 - self.cut**2)

    def local_distance(self, p):
        r, t, h, w = self.radius, 0.5 * self.thickness, self.cut, self._rim()
        rho, z = np.hypot(p[:, 0], p[:, 1]), p[:, 2]
        # above the cone through the rim circle the nearest point is on the rim
        near_rim = h * rho < w * z
        d = np.where(near_rim, np.hypot(rho - w, z - h), np.abs(np.hypot(rho, z) - r))
        return d - t

    @property
    def bounding_radius(self):
        return self.radius + 0.5 * self.thickness

    def shape_params(self):
        return [self.radius, 0.5 * self.thickness, self.cut, self._rim()]


@dataclass
class TwoBodies(SdfSolid):
    """A ball and a rounded cube side by side along local x, `gap` mm apart (min of exact
    SDFs of disjoint bodies: exact)."""

    sphere_radius: float = 10.0
    box_size: float = 16.0
    box_rounding: float = 2.0
    gap: float = 6.0
    tilt: Vec3 = (20.0, 30.0, 40.0)
    kind = "two-bodies"

    def _check_params(self):
        if not (
            self.sphere_radius > 0
            and self.box_size > 0
            and 0 <= self.box_rounding < self.box_size / 2
            and self.gap > 0
        ):
            raise ClrefractError(
                f"{self.kind}: need sphere_radius, box_size, gap > 0 and 0 <= box_rounding < "
                f"box_size/2, got {self.sphere_radius}, {self.box_size}, {self.box_rounding}, "
                f"{self.gap}"
            )

    def _centres(self) -> tuple[float, float]:
        """x of the ball and of the box, the pair centred on the local origin."""
        left = -(0.5 * self.gap + 2 * self.sphere_radius)
        right = 0.5 * self.gap + self.box_size
        shift = -0.5 * (left + right)
        return -(0.5 * self.gap + self.sphere_radius) + shift, 0.5 * (
            self.gap + self.box_size
        ) + shift

    def local_distance(self, p):
        xs, xb = self._centres()
        ball = np.linalg.norm(p - np.array([xs, 0.0, 0.0]), axis=-1) - self.sphere_radius
        b = 0.5 * self.box_size - self.box_rounding
        box = _rounded_box(p - np.array([xb, 0.0, 0.0]), b, self.box_rounding)
        return np.minimum(ball, box)

    @property
    def bounding_radius(self):
        xs, xb = self._centres()
        b = 0.5 * self.box_size - self.box_rounding
        return max(abs(xs) + self.sphere_radius, abs(xb) + math.sqrt(3.0) * b + self.box_rounding)

    def shape_params(self):
        xs, xb = self._centres()
        b = 0.5 * self.box_size - self.box_rounding
        return [xs, self.sphere_radius, xb, b, self.box_rounding]


@dataclass
class Vase(SdfSolid):
    """Solid of revolution about local z, |z| <= height/2, with the concave (waisted) profile
    r(z) = waist + k (z - waist_z)^2, k set so that r(height/2) = top.

    SDF: max((rho - r(z)) / sqrt(1 + r'(z)^2), |z| - height/2); the first term is the distance
    to the profile to first order (unit gradient on the surface), not exactly a distance away
    from it, so `lipschitz` bounds its gradient over the bounding sphere."""

    height: float = 40.0
    waist: float = 7.5
    top: float = 14.0
    waist_z: float = -4.0
    tilt: Vec3 = (15.0, 10.0, 0.0)
    kind = "vase"

    def _check_params(self):
        if not (
            self.height > 0 and 0 < self.waist < self.top and abs(self.waist_z) < self.height / 2
        ):
            raise ClrefractError(
                f"{self.kind}: need height > 0, 0 < waist < top and |waist_z| < height/2, got "
                f"height={self.height}, waist={self.waist}, top={self.top}, "
                f"waist_z={self.waist_z}"
            )
        self.lipschitz = self._lipschitz_bound()

    @property
    def _k(self) -> float:
        return (self.top - self.waist) / (0.5 * self.height - self.waist_z) ** 2

    def profile(self, z):
        return self.waist + self._k * (np.asarray(z) - self.waist_z) ** 2

    def _lipschitz_bound(self) -> float:
        """max |grad| of the side term over the bounding sphere's (rho, z) range, on a fine
        grid with a 2% margin (the gradient varies slowly: r'' is constant)."""
        rb = self.bounding_radius
        rho, z = np.meshgrid(np.linspace(0, rb, 401), np.linspace(-rb, rb, 801))
        k = self._k
        rp = 2 * k * (z - self.waist_z)
        s = np.sqrt(1 + rp * rp)
        gz = -rp / s - (rho - self.profile(z)) * rp * (2 * k) / s**3
        g = np.sqrt(1 / s**2 + gz**2)
        return max(1.0, 1.02 * float(g.max()))

    def local_distance(self, p):
        rp = 2 * self._k * (p[:, 2] - self.waist_z)
        side = (np.hypot(p[:, 0], p[:, 1]) - self.profile(p[:, 2])) / np.sqrt(1 + rp * rp)
        return np.maximum(side, np.abs(p[:, 2]) - 0.5 * self.height)

    @property
    def bottom(self) -> float:
        return float(self.profile(-0.5 * self.height))

    @property
    def bounding_radius(self):
        return math.hypot(max(self.top, self.bottom), 0.5 * self.height)

    def shape_params(self):
        return [0.5 * self.height, self.waist, self.waist_z, self._k]


@dataclass
class RandomSolid(SdfSolid):
    """Seeded random smooth solid: a smooth union (blend radius `blend`) of 3 to 5 capsules
    (a segment a-b thickened by a radius), the first centred on the origin. Capsules are exact
    SDFs and the polynomial smooth union keeps the bound, so the SDF is distance-like.
    `capsules` ([ax, ay, az, bx, by, bz, radius] each) is drawn from `seed` when empty, and
    kept in scene.json so a dataset can be rebuilt without the generator."""

    seed: int = 0
    blend: float = 5.0
    capsules: list = field(default_factory=list)
    kind = "random"

    def _check_params(self):
        _check_seed(self.kind, self.seed)
        if not self.blend > 0:
            raise ClrefractError(f"{self.kind}: blend must be positive, got {self.blend}")
        if not self.capsules:
            self.capsules = self._draw(int(self.seed))
        caps = np.asarray(self.capsules, float)
        if caps.ndim != 2 or caps.shape[1] != 7 or len(caps) == 0:
            raise ClrefractError(f"{self.kind}: capsules must be rows of 7 numbers")
        if not (np.all(np.isfinite(caps)) and np.all(caps[:, 6] > 0)):
            raise ClrefractError(f"{self.kind}: capsule radii must be positive and finite")
        self.capsules = caps.tolist()

    @staticmethod
    def _draw(seed: int) -> list:
        rng = np.random.default_rng(seed)
        caps = []
        for i in range(int(rng.integers(3, 6))):
            u = rng.normal(size=3)
            c = np.zeros(3) if i == 0 else 7.0 * rng.uniform() ** (1 / 3) * u / np.linalg.norm(u)
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            half = rng.uniform(5.0, 8.0) if i == 0 else rng.uniform(2.0, 8.0)
            caps.append([*(c - half * axis), *(c + half * axis), rng.uniform(5.0, 8.0)])
        return caps

    def local_distance(self, p):
        d = None
        for row in self.capsules:
            a, b, r = np.asarray(row[:3]), np.asarray(row[3:6]), row[6]
            pa, ba = p - a, b - a
            t = np.clip((pa @ ba) / max(float(ba @ ba), 1e-30), 0.0, 1.0)
            di = np.linalg.norm(pa - t[:, None] * ba, axis=-1) - r
            d = di if d is None else _smin(d, di, self.blend)
        return d

    @property
    def bounding_radius(self):
        caps = np.asarray(self.capsules, float)
        ends = np.maximum(np.linalg.norm(caps[:, :3], axis=1), np.linalg.norm(caps[:, 3:6], axis=1))
        # the smooth union bulges at most blend/4 beyond the plain union
        return float((ends + caps[:, 6]).max() + 0.25 * self.blend)

    def kernel_defines(self):
        return {**super().kernel_defines(), "NPRIM": len(self.capsules)}

    def shape_params(self):
        return [self.blend, *np.asarray(self.capsules, float).ravel()]


@dataclass
class Faceted(SdfSolid):
    """Seeded random cut stone: the intersection of 8 to 14 half-spaces n . p <= d (unit
    normals drawn evenly at random, offsets 9 to 15 mm), flat faces meeting at sharp edges
    and corners. The signed distance max(n . p - d) is exact inside and a lower bound outside
    (1-Lipschitz). `faces` ([nx, ny, nz, d] each) is drawn from `seed` when empty, until the
    faces close a solid within 30 mm, and kept in scene.json."""

    seed: int = 0
    faces: list = field(default_factory=list)
    kind = "faceted"

    def _check_params(self):
        _check_seed(self.kind, self.seed)
        if not self.faces:
            self.faces = self._draw(int(self.seed))
        f = np.asarray(self.faces, float)
        if f.ndim != 2 or f.shape[1] != 4 or len(f) < 4 or not np.all(np.isfinite(f)):
            raise ClrefractError(f"{self.kind}: faces must be 4 or more rows of 4 finite numbers")
        if not np.all(f[:, 3] > 0) or np.any(np.linalg.norm(f[:, :3], axis=1) == 0):
            raise ClrefractError(f"{self.kind}: faces need nonzero normals and offsets > 0")
        f[:, :3] /= np.linalg.norm(f[:, :3], axis=1, keepdims=True)
        self.faces = f.tolist()
        if not np.isfinite(self._corner_radius()):
            raise ClrefractError(f"{self.kind}: the faces close no solid")

    @staticmethod
    def _draw(seed: int) -> list:
        rng = np.random.default_rng(seed)
        while True:
            k = int(rng.integers(8, 15))
            n = rng.normal(size=(k, 3))
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            faces = np.column_stack([n, rng.uniform(9.0, 15.0, k)])
            if corner_radius(faces) <= 30.0:
                return faces.tolist()

    def _corner_radius(self) -> float:
        return corner_radius(np.asarray(self.faces, float))

    def local_distance(self, p):
        f = np.asarray(self.faces, float)
        return (p @ f[:, :3].T - f[:, 3]).max(axis=1)

    @property
    def bounding_radius(self):
        return self._corner_radius()

    def kernel_defines(self):
        return {**super().kernel_defines(), "NPRIM": len(self.faces)}

    def shape_params(self):
        return np.asarray(self.faces, float).ravel().tolist()


SHAPES = {
    c.kind: c
    for c in (SdfSphere, RoundedCube, Cylinder, Bowl, TwoBodies, Vase, RandomSolid, Faceted)
}
FAMILY = ("rounded-cube", "cylinder", "bowl", "two-bodies", "vase", "random", "faceted")


def make_shape(name: str, eta: float | None = None, tilt=None, seed: int | None = None):
    """A family shape by its CLI name with its default parameters; `seed` shapes `random`."""
    if name not in FAMILY:
        raise ClrefractError(f"unknown family shape {name!r}; shapes are {', '.join(FAMILY)}")
    kw = {}
    if eta is not None:
        kw["eta"] = eta
    if tilt is not None:
        kw["tilt"] = tilt
    if name in ("random", "faceted") and seed is not None:
        kw["seed"] = seed
    return SHAPES[name](**kw)


def shape_from_dict(d: dict) -> SdfSolid:
    """Rebuild a shape from its to_dict() (scene.json's object)."""
    kind = d.get("kind") if isinstance(d, dict) else None
    if kind not in SHAPES:
        raise ClrefractError(f"not a family shape: {kind!r}; kinds are {', '.join(SHAPES)}")
    try:
        return SHAPES[kind](**{k: v for k, v in d.items() if k != "kind"})
    except TypeError as exc:
        raise ClrefractError(f"{kind}: bad parameters ({exc})") from None


def parse_tilt(text: str) -> tuple[float, float, float]:
    """'a/b/c' -> rotation angles in degrees about x, y, z."""
    parts = str(text).split("/")
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        raise ClrefractError(f"--tilt must be three angles in degrees as a/b/c, got {text!r}")
    return vals
