"""One adapter per field kind: what a fit does differently for a voxel grid, a level set, a
hash grid, a sharp interface and a polytope. The rest of the fit asks its adapter
(`kind_of(cfg)`) and never the kind's name, as the tracer asks a field for its kernel
sources.
"""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np

from ..errors import ClrefractError
from ..limits import check_grid, check_table
from .config import FitConfig, coerced

# a line-search step costs tens of seconds (a hash grid's refit included), and the quick
# sphere's held-out loss still fell at step 15 of 16
LINE_SEARCH_ITERATIONS = 16
# with the grid fitted to the best step alone (refit = "best"), a step takes half the time
# it took with a refit after each: 32 steps cost what 16 did, and the quick sphere's
# held-out loss fell up to step 30
HASHGRID_LINE_SEARCH_ITERATIONS = 32
# in 16 runs of 32 line-search steps (sphere, drop, prism, cylinder, random solid) a better
# held-out loss came at most 13 steps after the one before; the prism's last at step 3 to 8
LINE_SEARCH_PATIENCE = 16
# what a hash grid from the hull fits with unless told otherwise. Adam on its tables and MLP
# added nothing; the line search on its level set, at a 0.5 mm interface (the true sphere
# on it renders 34.6 dB against 31.6 at 1 mm) and 32,768 rays a step, took the quick
# protocol's sphere from 31.69 to 33.65 dB in 12 steps and 34.32 in 20 (best step 18)
HASHGRID_HULL_DEFAULTS = dict(width=0.5, optimizer="line-search", line_batch=32768)


# a sharp surface from the hull, by smoothed descent (optimizers.SmoothedDescent). Adam's
# per-node steps, at any rate, took the test views down. Steps of at most 0.02 mm, smoothed
# over 4 mm: the 64 x 64 sphere from 30.6 to 55.6 dB in 600 steps (0.05 mm: 50.0 in 300,
# but the quick drop fell before it climbed); still climbing at 1,000 on the quick sphere
INTERFACE_DEFAULTS = dict(
    optimizer="descent", lr_phi=0.02, lr_index=0.001, iterations=1000, validate_every=50
)


# a graded medium by smoothed descent (optimizers.SmoothedDescent), most rays from the
# masks, a ray's gradient dropped once its adjoint grows 3 times (caustics: the exact
# gradient's step raised the loss at every length). On 40 views of 64 x 64, a 32^3 grid and
# 400 steps: Adam (5e-3 or 1e-3, from empty space or the hull) kept its start on the blob
# cluster and the Luneburg lens; this took the blobs from empty space to 0.07 of their
# held-out loss (24.66 to 35.42 dB, eta RMSE 0.0067 to 0.0002) and the lens from the hull to
# 0.69 (24.61 to 25.77 dB); with a growth of 30 and 4 mm, 0.26 and 0.97. A second
# smoothing, narrowing to 2 mm over the first half, beside the 8 mm one, each its own step:
# on those 40 views (32^3, where 2 mm is 4), the blob cluster 27.01 -> 35.66 dB, the lens
# 25.77 -> 25.56; the two sharing one step, 33.00 and 25.49; the narrowing one alone 33.39
# and 24.89 (on the quick protocol 39.57 for a cluster, 25.95 for the lens; to 1 mm, 37.70
# and 25.68). The quasi-Newton finish's 32 evaluations on 12 batches (fit/quasi_newton.py),
# quick graded set, test PSNR from the descent's grid: plume 74.33 -> 76.16 (ceiling 77.73),
# blob clusters +0.1 to +1.1 dB over the last runs without it, the GRIN rod and lens within
# 0.2 dB (the Luneburg lens's never kept: 28.49 dB, within its runs' spread); 96 to 172 s a fit
VOXEL_DEFAULTS = dict(
    optimizer="descent",
    lr=5e-3,
    mask_share=0.8,
    adjoint_growth_max=3.0,
    descent_sigma=8.0,
    descent_sigma_final=2.0,
    quasi_newton=32,
)


# the index's rate (its constant and a graded interior's terms) where the interior is graded:
# quick grin-ball (interface) 36.84 dB at 0.001, 38.83 at 0.003; grin-stone seed 0 (polytope)
# 29.38 and 29.93 (one index: 31.91 and 28.92)
GRADED_LR_INDEX = 0.003


def interior_defaults(items: dict) -> None:
    """A graded interior's rate, unless given (before the kind's own defaults)."""
    if items.get("interior") == "quadratic":
        items.setdefault("lr_index", GRADED_LR_INDEX)


def surface_params(cfg: FitConfig, params: np.ndarray) -> np.ndarray:
    """The surface's share of a run's parameters (a view, ending in its index): all of them,
    or those before a graded interior's terms."""
    if cfg.interior != "quadratic":
        return params
    from ..fields.interior import N_COEFFS

    return params[: len(params) - (N_COEFFS - 1)]


def interface_step_scale(index: float) -> float:
    """Factor on the default tracer step across a surface of glass up to this index: 1 up
    to 1.5, below in proportion to the index contrast above it, so that a ray bends as much
    per step (at 1.9 a quarter of a 1 mm interface made the truth's loss lowest at index
    1.8, an eighth at 1.9)."""
    return min(1.0, 0.5 / max(index - 1.0, 1e-6))


def voxel_step(box, res: int) -> float:
    """A voxel fit's default step: half a cell of its final grid. The truth sampled on the
    grid (luneburg, plume, sphere; 16^3 to 128^3 over 100 mm) renders the test views within
    0.04 dB of a quarter cell's PSNR at half a cell; 1 mm loses 0.33 to 0.44 dB on the
    sphere at 96^3 and 128^3 and a whole cell up to 0.25 dB, while at 16^3 and 32^3 half a
    cell takes 0.3 to 0.6 times 1 mm's steps."""
    return 0.5 * float(np.min(box.size)) / (res - 1)


class FieldKind:
    """The defaults, checks, field, step and strategies of one kind of fitted field."""

    name = ""
    candidates: tuple = ()  # kinds an automatic start chooses among (none: this one)
    grid = False  # a node grid of `res` per axis
    interface = False  # a surface, whose step shrinks for glass of a high index
    holds_interior = False  # a sharp surface whose interior can be graded (fields/interior.py)
    optimizers = ("adam",)

    # --- configuration ---------------------------------------------------------------------
    def defaults(self, items: dict) -> None:
        """Fill the keys a file or the flags left out with this kind's and its optimiser's
        defaults (written into config.toml like any other value)."""
        if items.get("optimizer") == "line-search":
            items.setdefault("iterations", self.line_search_iterations)
            # a step is a move that the held-out views must confirm: each one is validated
            items.setdefault("validate_every", 1)
            items.setdefault("patience", LINE_SEARCH_PATIENCE)

    line_search_iterations = LINE_SEARCH_ITERATIONS

    def validate(self, cfg: FitConfig) -> None:
        if cfg.optimizer not in self.optimizers:
            raise ClrefractError(self.optimizer_refusal)
        if cfg.skip_empty and self.skipping_kind(cfg) is None:
            raise ClrefractError(
                "skip_empty cannot train a hash grid: its parameters change eta anywhere "
                "(hashed table entries, the MLP); fit a voxel grid or level set, or set "
                "skip_empty = false"
            )
        if cfg.interior == "auto" and not self.candidates:
            raise ClrefractError(
                "interior 'auto' is the model choice's (field 'auto'); a field of one kind "
                "takes interior 'constant' or 'quadratic'"
            )
        if cfg.interior == "quadratic" and not self.holds_interior:
            raise ClrefractError(
                f"interior 'quadratic' grades the index inside a sharp surface: field "
                f"'interface' or 'polytope', not {self.name!r}"
            )

    optimizer_refusal = ""

    def step_mm(self, cfg: FitConfig) -> float:
        """The tracer's step: the configured one, else this kind's default."""
        return cfg.step if cfg.step > 0 else self.default_step(cfg)

    def default_step(self, cfg: FitConfig) -> float:
        return 1.0

    def skipping_kind(self, cfg: FitConfig) -> str | None:
        """The kind of field whose rays skip empty space with skip_empty (None: none may)."""
        return self.name

    def guided(self, cfg: FitConfig) -> bool:
        """Whether the fit's steps move another field (its guide: guide_config) that this
        field is fitted to."""
        return False

    def shows_guide(self, cfg: FitConfig) -> bool:
        """Whether a run in progress shows its guide: the grid follows it only at the end."""
        return False

    def object_box(self, cfg: FitConfig) -> bool:
        """Whether the field lives in the box around the visual hull (not the dataset's)."""
        return False

    def start(self, cfg: FitConfig) -> str:
        """The name of the start strategy (starts.py)."""
        return "empty"

    # --- the field --------------------------------------------------------------------------
    def make(self, cfg: FitConfig, box, eta_max: float, res: int):
        """A fresh field of this kind (eta = 1 everywhere)."""
        raise NotImplementedError

    def with_interior(self, cfg: FitConfig, field):
        """`field` with a quadratic interior where the run's `interior` says so."""
        if not (self.holds_interior and cfg.interior == "quadratic"):
            return field
        from ..fields.interior import GradedInterface

        frame = cfg.interior_frame
        if not frame:  # the start's: graded where the surface was placed, and recorded
            graded = GradedInterface(field)
            cfg.interior_frame = (*graded.centre.tolist(), graded.scale)
            return graded
        return GradedInterface(field, centre=frame[:3], scale=frame[3])

    def run_field(self, cfg: FitConfig, box, eta_max: float, res: int):
        """The field a run's checkpoint holds (`make`'s, graded as the run says): a start
        makes its own surface and grades it when it is placed (Fit.start)."""
        return self.with_interior(cfg, self.make(cfg, box, eta_max, res))

    def resolution(self, field) -> int:
        """The grid's nodes per axis (0: no grid), as checkpoint.npz's `shape` holds it."""
        return int(field.values.shape[0]) if self.grid else 0

    def eta_top(self, cfg: FitConfig, index: float) -> float:
        """The field's eta_max for glass of this index."""
        return index

    def with_top(self, field, eta_max: float) -> None:
        """The field's upper bound moved to eta_max (a hash grid follows its guide's index)."""

    def project(self, cfg: FitConfig, params, eta_max: float, free) -> None:
        """Keep parameters physical after an optimiser's step."""

    def extra_gradient(self, cfg: FitConfig, params):
        """Gradient of this kind's own penalties (0: none)."""
        return 0.0

    def frees_near_hull(self, cfg: FitConfig) -> bool:
        """Whether only parameters near the visual hull may move (`free_nodes`)."""
        return False

    def free_nodes(self, cfg: FitConfig, hull) -> np.ndarray | None:
        """Parameters that may move, of a field on the hull's grid (None: all)."""
        return None

    def sized_early(self, cfg: FitConfig) -> bool:
        """Whether the field's size (res = 0, n_max = 0) and step are resolved before the
        start: its box is the dataset's, not the hull's."""
        return False

    def early_step(self, box, cfg: FitConfig) -> float:
        return 0.0

    def resolution_at(self, cfg: FitConfig, it: int) -> int:
        """The grid resolution at an iteration (coarse to fine where the kind has one)."""
        return cfg.res if self.grid else 0

    # what Adam's run does after it takes its best parameters (optimizers.ADAM_FINISHES)
    adam_finish = ""

    # --- smoothed descent (optimizers.SmoothedDescent) ----------------------------------------
    def descent_grid(self, field) -> tuple:
        """The shape of the node grid at the front of the field's parameters."""
        return field.values.shape

    def descent_rates(self, cfg: FitConfig) -> tuple[float, float]:
        """The largest move of a grid node per step, and of each scalar after the grid."""
        return cfg.lr, 0.0

    def descent_row(self, field) -> dict:
        """What a descent step adds to its metrics row."""
        return {}

    # whether a descent's first step chooses the run's rate (SmoothedDescent._calibrate)
    calibrates_descent = False

    # --- empty-space skipping while it trains (occupancy.py) ---------------------------------
    def occupancy_slack(self, every: int, lr_phi: float) -> float:
        """How far the field's surface may move between two rebuilds (mm)."""
        return 0.0

    def snapshot(self, field):
        """What a rebuild remembers of the field (None: nothing)."""
        return None

    def moved_past(self, field, snapshot, slack: float) -> bool:
        """Whether the field moved further than the slack since `snapshot`."""
        return False

    def unchanged(self, field, snapshot) -> bool:
        """Whether the field is as it was at `snapshot` (False where nothing was kept)."""
        return False

    def live_cells(self, field, box, res: int, slack: float, free) -> np.ndarray:
        """The cells where eta varies now or can before the next rebuild."""
        return np.ones((res,) * 3, bool)


class VoxelKind(FieldKind):
    name = "voxel"
    grid = True
    calibrates_descent = True  # eta's contrast, unlike a surface's move in mm, spans 400x
    optimizers = ("adam", "descent")
    optimizer_refusal = (
        "optimizer 'line-search' moves a surface (a level set's, or the one a hash grid "
        "is distilled from); field 'voxel' uses optimizer 'adam' or 'descent'"
    )

    def defaults(self, items):
        for k, v in VOXEL_DEFAULTS.items():
            items.setdefault(k, v)
        frees_near_hull = items.get("init", FitConfig.init) == "hull" and (
            items.get("free_cells", FitConfig.free_cells) >= 0
        )
        if frees_near_hull and items.get("adjoint") != "discrete":
            # rays fly past the nodes held at 1: the same gradient, and on the quick Luneburg
            # lens 63 steps a ray instead of 143
            items.setdefault("skip_empty", True)
        super().defaults(items)

    def validate(self, cfg):
        super().validate(cfg)
        if cfg.res:  # 0: sized from the photographs
            check_grid("res", cfg.res)

    def start(self, cfg):
        return "voxel-hull" if cfg.init == "hull" else "empty"

    def make(self, cfg, box, eta_max, res):
        from ..fields.voxel import VoxelGrid

        return VoxelGrid(np.ones((res, res, res)), box, interp=cfg.interp, eta_max=eta_max)

    def eta_top(self, cfg, index):
        return index

    def project(self, cfg, params, eta_max, free):
        np.clip(params, 1.0, eta_max, out=params)  # node values physical: 1 <= eta <= eta_max
        if free is not None:
            params[~free] = 1.0

    def extra_gradient(self, cfg, params):
        return cfg.sparsity * (params > 1.0) if cfg.sparsity else 0.0

    def frees_near_hull(self, cfg):
        return cfg.init == "hull" and cfg.free_cells >= 0

    def free_nodes(self, cfg, hull):
        return hull.dilated(cfg.free_cells).ravel() if hull.found else None

    def sized_early(self, cfg):
        return True

    def early_step(self, box, cfg):
        return voxel_step(box, cfg.res)

    def live_cells(self, field, box, res, slack, free):
        from ..occupancy import live_cells_nodes

        if free is None:
            return np.ones((res,) * 3, bool)
        # nodes off 1 too: a hull filled wider than the free nodes, before the first step
        # resets them
        nodes = free.reshape(field.values.shape) | (field.values != 1.0)
        return live_cells_nodes(nodes, field, box, res)

    def resolution_at(self, cfg, it):
        """Coarse to fine: the schedule splits the first half of the iterations."""
        sched = [r for r in cfg.res_schedule if r < cfg.res]
        if not sched:
            return cfg.res
        span = cfg.iterations / 2 / len(sched)
        k = int(it // span)
        return sched[k] if k < len(sched) else cfg.res


class LevelSetKind(FieldKind):
    name = "levelset"
    grid = True
    interface = True
    optimizers = ("adam", "line-search")

    def validate(self, cfg):
        super().validate(cfg)
        if cfg.init != "hull":
            raise ClrefractError("a level-set fit starts from the visual hull (init = 'hull')")
        if cfg.res:
            check_grid("res", cfg.res)

    def default_step(self, cfg):
        return cfg.width / 4

    def object_box(self, cfg):
        return True

    def start(self, cfg):
        return "levelset-hull"

    def occupancy_slack(self, every, lr_phi):
        return 2.0 * every * lr_phi  # Adam moves a node by about its rate per step

    def snapshot(self, field):
        return field.phi.copy()

    def moved_past(self, field, snapshot, slack):
        return float(np.abs(field.phi - snapshot).max()) > slack

    def unchanged(self, field, snapshot):
        return snapshot is not None and np.array_equal(field.phi, snapshot)

    def live_cells(self, field, box, res, slack, free):
        from ..occupancy import live_cells_levelset

        return live_cells_levelset(field, box, res, slack)

    def make(self, cfg, box, eta_max, res):
        from ..fields.levelset import LevelSetField

        far = np.full((res, res, res), 4.0 * cfg.width)  # no surface: air everywhere
        return LevelSetField(far, box, eta=1.0, width=cfg.width, eta_max=eta_max)


class HashGridKind(FieldKind):
    name = "hashgrid"
    interface = True
    optimizers = ("adam", "line-search", "descent")
    line_search_iterations = HASHGRID_LINE_SEARCH_ITERATIONS

    def defaults(self, items):
        init = items.get("init", FitConfig.init)
        if items.get("optimizer", "descent" if init == "empty" else None) == "descent":
            # a graded medium: the grid follows a voxel grid's smoothed descent (its guide).
            # From empty space, 200 Adam steps at the hull's rates left a 30-view blob
            # cluster at 0.97 of its held-out loss, in 14 minutes
            items.setdefault("optimizer", "descent")
            for k, v in VOXEL_DEFAULTS.items():
                items.setdefault(k, v)
        elif init == "hull":
            for k, v in HASHGRID_HULL_DEFAULTS.items():
                items.setdefault(k, v)
        super().defaults(items)
        if items.get("optimizer") == "line-search" and init == "hull":
            if items.get("adjoint") != "discrete":
                # the level set it follows skips (the grid's own rays never do): exact in
                # float64, and the quick drop's fit took 1,203 s instead of 1,497
                items.setdefault("skip_empty", True)

    def validate(self, cfg):
        if cfg.optimizer == "line-search" and cfg.init != "hull":
            raise ClrefractError(
                "optimizer 'line-search' moves a hash grid's surface from the visual hull: "
                "set init = 'hull'"
            )
        super().validate(cfg)
        if cfg.output == "ramp" and cfg.init != "hull":
            raise ClrefractError(
                "a hash grid with the ramp output starts from the visual hull (init = 'hull'):"
                " from empty space its output is flat and has no gradient"
            )
        if cfg.output == "ramp" and cfg.optimizer == "descent":
            raise ClrefractError(
                "a hash grid's descent follows a graded medium's voxel grid: use output = "
                "'sigmoid' (a ramp holds a surface)"
            )
        check_table(cfg.levels, cfg.log2_table, cfg.features)
        from ..limits import check_count

        check_count("hidden", cfg.hidden, 1, 1024)

    def output(self, cfg) -> str:
        """ "ramp" from the hull (an interface), "sigmoid" from empty space, unless told."""
        return cfg.output or ("sigmoid" if self.graded(cfg) or cfg.init != "hull" else "ramp")

    def default_step(self, cfg):
        # a quarter of the interface: at half, the truth fitted into a hash grid renders
        # 5 dB worse (a 48 x 48 sphere, width 1 mm: 24.5 against 29.3 dB). A sigmoid hash
        # grid's surface ramps over a quarter of the width (fit_surface): an eighth
        return cfg.width / 4 if self.output(cfg) == "ramp" else cfg.width / 8

    def sized_early(self, cfg):
        return not self.object_box(cfg)  # a graded medium in the dataset's box

    def early_step(self, box, cfg):
        """From empty space, half a cell of the finest level, as a voxel grid's step: a
        graded medium has no interface to step across."""
        return voxel_step(box, cfg.n_max)

    def skipping_kind(self, cfg):
        return guide_kind(cfg) if self.guided(cfg) else None

    def guided(self, cfg):
        return self.graded(cfg) or (cfg.init == "hull" and cfg.optimizer == "line-search")

    def shows_guide(self, cfg):
        return self.graded(cfg) or self.guided(cfg) and cfg.refit == "best"

    def graded(self, cfg) -> bool:
        """Whether the grid follows a voxel grid's smoothed descent (a graded medium)."""
        return cfg.optimizer == "descent"

    def object_box(self, cfg):
        return cfg.init == "hull" and not self.graded(cfg)

    def start(self, cfg):
        if self.graded(cfg):
            return "voxel-guide"
        return "distilled" if cfg.init == "hull" else "empty"

    def make(self, cfg, box, eta_max, res):
        from ..fields.hashgrid import HashGridField

        return HashGridField(hashgrid_config(cfg, eta_max), box, seed=cfg.seed)

    def eta_top(self, cfg, index):
        """A sigmoid's eta_max lies index_headroom above the index: the MLP's output is then
        6 inside the glass, where the sigmoid is saturated and keeps eta flat (noise in grad
        eta there bends every ray crossing it); a ramp's is the index itself."""
        room = cfg.index_headroom if self.output(cfg) == "sigmoid" else 0.0
        return 1 + (index - 1) * (1 + room)

    def with_top(self, field, eta_max):
        if eta_max != field.config.eta_max:
            field.config = replace(field.config, eta_max=float(eta_max))


class InterfaceKind(LevelSetKind):
    """A level set's surface at zero width: rays refract at it by Snell's law
    (fields/interface.py), with the level set's start and parameters."""

    name = "interface"
    interface = False  # no ramp to step across: no step at all
    holds_interior = True
    optimizers = ("descent", "adam", "line-search")
    optimizer_refusal = "field 'interface' uses optimizer 'descent', 'adam' or 'line-search'"

    def defaults(self, items):
        interior_defaults(items)
        for k, v in INTERFACE_DEFAULTS.items():
            items.setdefault(k, v)
        super().defaults(items)

    def skipping_kind(self, cfg):
        return None  # straight segments need no empty-space skipping

    def make(self, cfg, box, eta_max, res):
        from ..fields.interface import InterfaceField

        far = np.full((res, res, res), 4.0 * cfg.width)  # no surface: air everywhere
        return InterfaceField(far, box, eta=1.0, width=cfg.width, eta_max=eta_max)

    def descent_grid(self, field):
        return field.phi.shape

    def descent_rates(self, cfg):
        return cfg.lr_phi, cfg.lr_index

    def descent_row(self, field):
        return {"eta": field.eta}

    def project(self, cfg, params, eta_max, free):
        """Keep the box's two outer layers of nodes outside the solid: the box wall is air
        (phi there blends the outer two nodes)."""
        params = surface_params(cfg, params)
        n = round(len(params[:-1]) ** (1 / 3))
        phi = params[:-1].reshape(n, n, n)
        for a in range(3):
            for side in (slice(0, 2), slice(-2, None)):
                sl = [slice(None)] * 3
                sl[a] = side
                np.maximum(phi[tuple(sl)], 1e-3, out=phi[tuple(sl)])


# the edge roundings (mm) a polytope's start tries once its faces are placed, the loss
# choosing: a real glass cube or prism has its edges bevelled or polished round
POLYTOPE_ROUNDINGS = (0.0, 0.5, 1.0, 2.0, 3.0, 4.0)
# a convex solid of flat faces by Adam on its planes and index, from the hull's faces
# (starts.PolytopeHullStart), its rates decaying to 0.05 (from the true prism, undecayed
# rates of 0.02 mm left it at 36 dB). Quick protocol, all 20 test views, 0.02 / 0.01 mm:
# the prism 46.8 / 48.7 dB, three cut stones 30.1 / 36.9, 31.7 / 33.5, 30.9 / 36.3 (0.005:
# the first 32.2); at 0.02 a stone's held-out loss rose from its start in the first steps
POLYTOPE_DEFAULTS = dict(
    optimizer="adam",
    lr_phi=0.01,
    lr_index=0.001,
    lr_final=0.05,
    iterations=600,
    validate_every=50,
)


class PolytopeKind(FieldKind):
    """A convex solid bounded by planes, one index inside, Snell's law at its faces
    (fields/interface.py's PolytopeInterface): flat faces and sharp edges held exactly."""

    name = "polytope"
    holds_interior = True
    optimizers = ("adam",)
    optimizer_refusal = "field 'polytope' uses optimizer 'adam'"

    def defaults(self, items):
        interior_defaults(items)
        for k, v in POLYTOPE_DEFAULTS.items():
            items.setdefault(k, v)
        super().defaults(items)

    def validate(self, cfg):
        super().validate(cfg)
        if cfg.init != "hull":
            raise ClrefractError("a polytope fit starts from the visual hull (init = 'hull')")
        if cfg.res:  # no grid here, but a grid size none can take is refused as for any kind
            check_grid("res", cfg.res)

    def skipping_kind(self, cfg):
        return None  # straight segments need no empty-space skipping

    def object_box(self, cfg):
        return True

    def start(self, cfg):
        return "polytope-hull"

    def resolution(self, field) -> int:
        return field.n_planes  # what a checkpoint's `shape` holds: the face count

    def make(self, cfg, box, eta_max, res):
        """res faces about the box's centre, far out, of index 1: air everywhere."""
        from ..facets import spread_normals

        n = spread_normals(max(res, 4))
        far = float(np.linalg.norm(box.size))
        return self.make_planes(cfg, box, eta_max, np.column_stack([n, np.full(len(n), far)]))

    def make_planes(self, cfg, box, eta_max, planes, eta: float = 1.0, rounding=None):
        """A polytope of these planes, its edges rounded as `rounding` says (None: as the
        configuration does, sharp while the start has yet to choose)."""
        from ..fields.interface import PolytopeInterface

        rounding = max(cfg.rounding, 0.0) if rounding is None else rounding
        return PolytopeInterface(planes, eta, box, eta_max=eta_max, rounding=rounding)

    adam_finish = "face-offsets"

    def project(self, cfg, params, eta_max, free):
        """Unit normals (the planes are the same; Adam's steps keep their scale), and the
        index within [1, eta_max]."""
        params = surface_params(cfg, params)
        rows = params[:-1].reshape(-1, 4)
        rows[:, :3] /= np.linalg.norm(rows[:, :3], axis=1, keepdims=True)
        params[-1] = min(max(params[-1], 1.0), eta_max)


class AutoKind(FieldKind):
    """No kind yet: the start tries each candidate, and the run goes on with the one whose
    start the held-out views prefer (session.choose_model): a sharp surface for glass and
    water, flat faces for cut glass, a grid of eta for a graded medium."""

    name = "auto"
    candidates = ("interface", "polytope", "voxel")
    optimizers = ("adam", "line-search", "descent")

    def defaults(self, items):
        items.setdefault("interior", "auto")  # the rest: each candidate's own, when tried

    def usable(self, cfg) -> tuple:
        """The candidates this configuration can run (an interface starts from the hull)."""
        ok, refusal = [], None
        for name in self.candidates:
            try:
                KINDS[name].validate(candidate_config(cfg, name))
                ok.append(name)
            except ClrefractError as exc:
                refusal = refusal or exc
        if not ok:
            raise refusal
        return tuple(ok)

    def validate(self, cfg):
        self.usable(cfg)

    def make(self, cfg, box, eta_max, res):
        raise ClrefractError("field 'auto' is chosen at the start; it makes no field itself")


KINDS = {
    k.name: k
    for k in (
        VoxelKind(),
        LevelSetKind(),
        HashGridKind(),
        InterfaceKind(),
        PolytopeKind(),
        AutoKind(),
    )
}


def candidate_config(cfg: FitConfig, name: str, interior: str = "") -> FitConfig:
    """An automatic run's configuration for one candidate kind: the values it was given
    (load_config's record; else those off FitConfig's defaults), `interior` where given,
    then that kind's defaults. The model choice's "auto" interior is one index here."""
    given = getattr(cfg, "given", None)  # load_config's record of the keys it was given
    items = {
        f.name: getattr(cfg, f.name)
        for f in fields(FitConfig)
        if f.name != "field"
        and (f.name in given if given is not None else getattr(cfg, f.name) != f.default)
    }
    items["field"] = name
    if interior or items.get("interior") == "auto":
        items["interior"] = interior or "constant"
    KINDS[name].defaults(items)
    return coerced(items)


def graded_candidate(cfg: FitConfig, name: str) -> FitConfig | None:
    """The model choice's graded variant of candidate `name` (interior = "auto" and a kind
    that holds an interior), else None."""
    if cfg.interior != "auto" or not KINDS[name].holds_interior:
        return None
    return candidate_config(cfg, name, "quadratic")


def kind_named(name: str) -> FieldKind:
    try:
        return KINDS[name]
    except KeyError:
        raise ClrefractError(f"field must be one of {', '.join(KINDS)}, got {name!r}") from None


def kind_of(cfg: FitConfig) -> FieldKind:
    return kind_named(cfg.field)


def make_field(cfg: FitConfig, box, eta_max: float, res: int):
    """A fresh field of the configured kind (eta = 1 everywhere)."""
    return kind_of(cfg).make(cfg, box, eta_max, res)


def hashgrid_config(cfg: FitConfig, eta_max: float = 1.6):
    """The hash grid a fit configuration describes."""
    from ..fields.hashgrid import HashGridConfig

    return HashGridConfig(
        levels=cfg.levels,
        features=cfg.features,
        log2_table=cfg.log2_table,
        n_min=cfg.n_min,
        n_max=cfg.n_max,
        hidden=cfg.hidden,
        layers=cfg.layers,
        eta_max=eta_max,
        output=HashGridKind().output(cfg),
    )


def step_mm(cfg: FitConfig) -> float:
    """The tracer step a run of this configuration traces (and is scored) with."""
    return kind_of(cfg).step_mm(cfg)


def guide_kind(cfg: FitConfig) -> str:
    """The kind of field a guided hash grid follows: a graded medium's voxel grid under the
    smoothed descent, else the level set of its line search."""
    return "voxel" if cfg.optimizer == "descent" else "levelset"


def guide_config(cfg: FitConfig, index: float) -> FitConfig:
    """The field a hash grid starts from and follows: a voxel grid with the fit's settings
    (bound as a voxel fit binds its grid: Fit.guide_bound), or a level set with a level
    set's own step at this glass index."""
    if guide_kind(cfg) == "voxel":
        return replace(cfg, field="voxel")
    guide = replace(cfg, field="levelset", step=0.0)
    guide.step = KINDS["levelset"].step_mm(guide) * interface_step_scale(index)
    return guide
