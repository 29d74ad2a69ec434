"""`clrefract fit`: recover eta(x) from a dataset with the adjoint gradient and Adam.

A run folder holds everything about one fit:
    config.toml        the resolved configuration
    metrics.jsonl      one JSON line per iteration
    checkpoint.npz     parameters, Adam state and iteration, written atomically
    field.npz          the fitted field, loadable by `clrefract render --field`
    loss.png, slices.png, test/ (renders of the test views), results.json, surface.ply
    (the surface the chamfer distance scores, as a mesh)
Batches, the environment blur and the grid resolution are functions of (seed, iteration),
so a resumed run repeats exactly what an uninterrupted one would have done.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from . import start_losses
from .adam import Adam
from .dataset import Dataset, box_of, box_values
from .errors import ClrefractError
from .fit_start import HullStart
from .imageio import atomic_path, ensure_out_dir
from .limits import check_fit_config
from .metrics import psnr_linear_batch
from .progress import Progress

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib


FIELDS = ("levelset", "voxel", "hashgrid")
GRID_FIELDS = ("levelset", "voxel")  # fields on a node grid of `res` per axis
# what a run folder holds that a new run would overwrite
RUN_FILES = ("checkpoint.npz", "field.npz", "results.json", "start.json", "run.json")


@dataclass
class FitConfig:
    field: str = "voxel"  # "levelset", "voxel" or "hashgrid"
    # voxel grid (level set: its grid of distances): final resolution, and the
    # coarse-to-fine resolutions before it (voxel grids only); 0: one cell per pixel
    # footprint at the object (clrefract/resolution.py), recorded in config.toml
    res: int = 64
    res_schedule: tuple = ()  # e.g. (16, 32); the hull start wants the final grid at once
    interp: str = "bspline"  # C2 tricubic B-spline; "smoothstep" (C1) or "trilinear"
    # level set: one index inside a surface ramped across `width` mm (a hash grid from
    # the hull: 0.5 unless told, as its optimizer and line_batch; HASHGRID_HULL_DEFAULTS)
    width: float = 1.0
    # Adam moves every band node by about its rate each step: from the level-set start on
    # 128 x 128 views, 0.02 and 0.005 mm climbed, 0.00125 mm (index 3e-4) descended
    lr_phi: float = 0.00125  # mm per step, the distance values
    lr_index: float = 3e-4  # the level set's index
    # hash grid
    levels: int = 8
    features: int = 2
    log2_table: int = 16
    n_min: int = 8
    n_max: int = 64  # finest level over the object's box: about 1 mm cells on 128 x 128 views
    # (0: one cell per pixel footprint, as res = 0)
    hidden: int = 32
    layers: int = 2
    eta_max: float = 0.0  # 0: the scene's upper eta bound (hash grid: see index_headroom)
    # the MLP's output o becomes eta through "ramp", the level set's C2 ramp over o in
    # [-1, 1] (eta exactly 1 and exactly eta_max beyond it: an interface as a level set's,
    # traced in steps of width/4), or "sigmoid" (smooth everywhere, what a start from empty
    # space needs; steps of width/8); "": ramp from the hull, sigmoid from empty space
    output: str = ""
    # a sigmoid hash grid from the hull starts with eta_max this far above the start's
    # index, in units of index - 1: the MLP's output is then 6 inside the glass, where the
    # sigmoid is saturated and keeps eta flat (noise in grad eta there bends every ray
    # crossing it); a ramp's eta_max is the index itself, flat past the ramp's top
    index_headroom: float = 0.0025
    # fitting the hash grid to the level-set start: the true sphere renders at 30.99 dB after
    # 1000 steps, 31.71 after 2000 (the level set itself: 31.86)
    distil_iterations: int = 2000
    # where that fitting (and each line-search step's refit) runs: "device", the fit's
    # OpenCL device in its precision (kernels_cl/hashgrid_distil.cl; 3.2x the host's steps
    # per second on this 2-core CPU), or "host", float64 NumPy on the host's cores
    distil_on: str = "device"
    # optimisation
    iterations: int = 600  # Adam's; a line search's default is LINE_SEARCH_ITERATIONS
    batch: int = 8192
    lr: float = 5e-3  # voxel values; the index of a level set
    # hash grid from its hull start: 1e-2 and 1e-3 raised the held-out loss of the drop,
    # these lowered it (by little)
    lr_table: float = 1e-3
    lr_mlp: float = 1e-4
    lr_final: float = 0.1  # learning rates decay exponentially to this fraction
    # "adam", or "line-search" (level sets: each step keeps the rays whose adjoint grows at
    # most keep_growth, smooths the phi gradient over the grad_sigma scales (cells, each
    # weighted by its square) and takes the best of line_steps mm along it;
    # clrefract/fit_linesearch.py): from the quick sphere's start
    # at 0.5 mm, 8 steps of 60,000 rays took the test views from 31.98 to 33.59 dB
    # (tools/diag_tame_descent.py). A hash grid from the hull moves the level set it was
    # distilled from that way, and is fitted to it (`refit`); it is that fit's default
    optimizer: str = "adam"
    keep_growth: float = 10.0
    grad_sigma: tuple = (3.0, 6.0, 12.0)
    line_steps: tuple = (0.003, 0.01, 0.03, 0.1)
    # index moves a line-search step tries after its shape move, down the kept rays' index
    # gradient (the best, or none); (): the index stays the start's
    index_steps: tuple = ()
    # a refit starts from the grid's last fit: on a sphere grown 0.1 mm a step, 100, 200 and
    # 300 iterations left eta RMS 0.00032, 0.00029 and 0.00028 after four steps
    refit_iterations: int = 200
    # "best": a hash grid's line search validates the level set it moves, and the grid is
    # fitted to the best step once, at the end; "step": after every move taken, and the grid
    # is validated (a refit and its validation were half of a step on the quick sphere)
    refit: str = "best"
    # after a line search, its best level set grown and its index moved together
    # (clrefract/size_search.py), kept where the held-out views agree
    size_search: bool = True
    line_batch: int = 0  # mask rays a line-search step takes (0: batch, as the start's search)
    reg: float = 1e-4  # weight of the smoothness regulariser
    sparsity: float = 0.0  # weight of an L1 pull of voxel values towards eta = 1 (empty space)
    # start: "hull" fills the visual hull of the refraction masks with the index that a
    # line search on the loss picks, and changes eta only near the hull; "empty": eta = 1
    init: str = "hull"
    mask_threshold: float = 0.05  # sRGB difference from the straight view that marks a pixel
    free_cells: int = 2  # cells around the hull where eta may change (-1: everywhere)
    hull_tolerance: float = 0.03  # fraction of the views a hull point may lie outside
    # a view whose mask carves more than this share of the other views' hull has holes, and
    # is left out of the hull (0: keep every view; clrefract/hull.py, carving_views)
    hull_carve: float = 0.02
    # level sets also try the hull tightened by silhouette-held curvature flow (flat faces
    # the views roof over come out flat; clrefract/hull_tighten.py), kept if its loss is lower
    tighten_hull: bool = True
    # level sets also try the hull hollowed to shells 2, 4 and 6 cells deep (a bowl, a glass:
    # a hollow that no silhouette shows, where the whole hull scores worse than air)
    shell_starts: bool = True
    # share of each training batch drawn from the refraction masks (grown by 2 pixels), the
    # rest from all pixels; 0: all pixels alike (a mask rarely covers more than a tenth)
    mask_share: float = 0.0
    # compare training images by blocks of this many pixels a side at first, halving to
    # single pixels by block_until of the iterations (0 or 1: pixels throughout): the loss of
    # block means is smooth over image shifts up to a block, and zero at the truth
    block: int = 0
    block_until: float = 0.5
    env_blur: float = 0.0  # initial environment blur in pixels, sharpened to 0
    blur_until: float = 0.5  # fraction of the iterations over which the blur goes to 0
    # mm; 0: width/4 for a level set and a hash grid (finer for glass above index 1.5,
    # interface_step_scale); half a cell of the final grid for a voxel grid; the start
    # resolves it into config.toml where it is not width/4 (voxel_step)
    step: float = 0.0
    # forward states kept every this many steps for the backward pass (0: constant memory);
    # they stop the re-integrated ray drifting away through sharp interfaces
    backward_checkpoints: int = 8
    # a ray's backward pass stops once its adjoint grew by this factor (0: never): rays that
    # wander inside an object have exponentially growing, useless gradients
    adjoint_growth_max: float = 30.0
    # backward pass: "continuous" (adjoint-state ODE, gradient up to the integrator's error)
    # or "discrete" (each step reversed exactly from the checkpoints above: the renderer's
    # own gradient, for about twice the field evaluations and K more states per ray)
    adjoint: str = "continuous"
    # empty-space skipping in the forward and backward passes: rays fly straight through
    # cells where eta cannot vary before the occupancy (occupancy_res^3 over the box) is
    # rebuilt from the parameters, every occupancy_every iterations (fit_occupancy.py: a
    # level set's band plus its drift, a voxel grid's free nodes). A hash grid's own rays
    # cannot skip; from the hull with the line search, the level set it follows (its start
    # search and its steps) does, by default (_field_defaults)
    skip_empty: bool = False
    occupancy_every: int = 25
    occupancy_res: int = 32
    precision: str = "float32"
    loss: str = "srgb"
    queues: int = 1
    lanes: int = 0  # 0: device default
    device: str = ""  # under MPI: a comma-separated list is indexed by local rank
    # under MPI, each batch is cut into this many pieces (a power of two) that are summed in
    # one fixed order: any number of ranks up to it gives the same gradient (parallel.py)
    chunks: int = 16
    seed: int = 0
    checkpoint_every: int = 50
    # loss on a fixed batch of training rays every this many iterations (0: never); the run
    # keeps the parameters that scored best there (at the final grid resolution)
    validate_every: int = 25
    # stop once this many validated steps in a row found no better held-out loss (0: run
    # every iteration); a line search's default is LINE_SEARCH_PATIENCE
    patience: int = 0
    # training views held out of the gradient for that validation (every k-th view; 0, or
    # fewer than five training views each: validate on training rays): what generalises to
    # new views, not what fits the training rays best
    val_views: int = 8
    # the run stops, keeping its best parameters, once the held-out loss exceeds its best by
    # this factor (0: never): a learning rate 2000x the default took a voxel fit's to 6.5x
    # within 5 iterations, and healthy fits stay near their best
    diverge_factor: float = 5.0
    test_views: int = -1  # test views rendered at the end (-1: all)
    # the object's box in mm, xmin, ymin, zmin, xmax, ymax, zmax (--box); (): the dataset's
    box: tuple = ()

    @property
    def step_mm(self) -> float:
        if self.step > 0:
            return self.step
        # a quarter of the interface: at half, the truth fitted into a hash grid renders
        # 5 dB worse (a 48 x 48 sphere, width 1 mm: 24.5 against 29.3 dB). A sigmoid hash
        # grid's surface ramps over a quarter of the width (fit_surface): an eighth
        if self.field == "hashgrid":
            return self.width / 4 if self.hashgrid_output == "ramp" else self.width / 8
        if self.field == "levelset":
            return self.width / 4
        return 1.0  # voxel runs from before voxel_step (a new run records its step)

    @property
    def hashgrid_output(self) -> str:
        return self.output or ("ramp" if self.init == "hull" else "sigmoid")

    def hashgrid_eta_max(self, index: float) -> float:
        """A hash grid's eta_max for glass of this index (index_headroom, sigmoid only)."""
        room = self.index_headroom if self.hashgrid_output == "sigmoid" else 0.0
        return 1 + (index - 1) * (1 + room)

    def skipping_field(self) -> str:
        """The kind of field whose rays skip empty space with skip_empty: a hash grid from
        the hull with the line search traces its level set (start search and steps)."""
        guided = self.init == "hull" and self.optimizer == "line-search"
        return "levelset" if self.field == "hashgrid" and guided else self.field

    def validate(self) -> None:
        if self.box:
            self.box = tuple(box_values(self.box, "box"))
        if self.field not in FIELDS:
            raise ClrefractError(f"field must be one of {', '.join(FIELDS)}, got {self.field!r}")
        check_fit_config(self)
        for name in ("iterations", "batch", "queues"):
            if getattr(self, name) < 1:
                raise ClrefractError(f"{name} must be at least 1, got {getattr(self, name)}")
        for name in ("res", "n_max"):
            if getattr(self, name) < 0:
                raise ClrefractError(
                    f"{name} must be at least 1 (or 0: from the photographs), "
                    f"got {getattr(self, name)}"
                )
        if not (self.step >= 0 and math.isfinite(self.step)):
            raise ClrefractError(f"step must be positive (or 0: automatic), got {self.step}")
        if not (self.width > 0 and math.isfinite(self.width)):
            raise ClrefractError(f"width must be positive, got {self.width}")
        if not (self.diverge_factor == 0 or 1 < self.diverge_factor < math.inf):
            raise ClrefractError(
                f"diverge_factor must be above 1 (or 0: never), got {self.diverge_factor}"
            )
        if not (0 <= self.index_headroom < 10):
            raise ClrefractError(f"index_headroom must be in [0, 10), got {self.index_headroom}")
        if not 0 <= self.hull_tolerance < 0.5:
            raise ClrefractError(
                "hull_tolerance must be in [0, 0.5) (a share of the views), "
                f"got {self.hull_tolerance}"
            )
        if not 0 <= self.hull_carve <= 1:
            raise ClrefractError(
                f"hull_carve must be in [0, 1] (a share of the hull; 0 keeps every view), "
                f"got {self.hull_carve}"
            )
        if not 0 < self.mask_threshold < 1:
            raise ClrefractError(
                f"mask_threshold must be in (0, 1) (an sRGB difference), got {self.mask_threshold}"
            )
        if self.free_cells < -1:
            raise ClrefractError(
                f"free_cells must be at least 0 (or -1: everywhere), got {self.free_cells}"
            )
        if self.output not in ("", "ramp", "sigmoid"):
            raise ClrefractError(f"output must be 'ramp' or 'sigmoid', got {self.output!r}")
        if self.field == "hashgrid" and self.output == "ramp" and self.init != "hull":
            raise ClrefractError(
                "a hash grid with the ramp output starts from the visual hull (init = 'hull'):"
                " from empty space its output is flat and has no gradient"
            )
        if self.field == "levelset" and self.init != "hull":
            raise ClrefractError("a level-set fit starts from the visual hull (init = 'hull')")
        if self.init not in ("hull", "empty"):
            raise ClrefractError(f"init must be 'hull' or 'empty', got {self.init!r}")
        from .gradient import ADJOINTS

        if self.adjoint not in ADJOINTS:
            raise ClrefractError(
                f"adjoint must be one of {', '.join(ADJOINTS)}, got {self.adjoint!r}"
            )
        if self.backward_checkpoints < 0:
            raise ClrefractError(
                f"backward_checkpoints must be >= 0, got {self.backward_checkpoints}"
            )
        if self.skip_empty:
            from .fit_occupancy import TrainingOccupancy

            TrainingOccupancy(
                self.skipping_field(), self.occupancy_res, self.occupancy_every, self.lr_phi
            )
            if self.adjoint == "discrete":
                raise ClrefractError(
                    "skip_empty needs adjoint = 'continuous': the discrete adjoint replays "
                    "every step"
                )
            if not 1 <= self.occupancy_res <= 1024:
                raise ClrefractError(f"occupancy_res must be 1 to 1024, got {self.occupancy_res}")
        if self.optimizer not in ("adam", "line-search"):
            raise ClrefractError(
                f"optimizer must be 'adam' or 'line-search', got {self.optimizer!r}"
            )
        if self.optimizer == "line-search":
            from .fit_linesearch import check_line_search

            check_line_search(self)
        if self.distil_on not in ("device", "host"):
            raise ClrefractError(f"distil_on must be 'device' or 'host', got {self.distil_on!r}")
        if self.interp not in ("smoothstep", "trilinear", "bspline"):
            raise ClrefractError(
                f"interp must be 'bspline', 'smoothstep' or 'trilinear', got {self.interp!r}"
            )


# a line-search step costs tens of seconds (a hash grid's refit included), and the quick
# sphere's held-out loss still fell at step 15 of 16
LINE_SEARCH_ITERATIONS = 16
# what a hash grid from the hull fits with unless told otherwise. Adam on its tables and MLP
# added nothing; the line search on its level set, at a 0.5 mm interface (the true sphere
# on it renders 34.6 dB against 31.6 at 1 mm) and 32,768 rays a step, took the quick
# protocol's sphere from 31.69 to 33.65 dB in 12 steps and 34.32 in 20 (best step 18)
HASHGRID_HULL_DEFAULTS = dict(width=0.5, optimizer="line-search", line_batch=32768)
# with the grid fitted to the best step alone (refit = "best"), a step takes half the time
# it took with a refit after each: 32 steps cost what 16 did, and the quick sphere's
# held-out loss fell up to step 30
HASHGRID_LINE_SEARCH_ITERATIONS = 32
# in 16 runs of 32 line-search steps (sphere, drop, prism, cylinder, random solid) a better
# held-out loss came at most 13 steps after the one before; the prism's last at step 3 to 8
LINE_SEARCH_PATIENCE = 16


def _field_defaults(items: dict) -> None:
    """Fill the keys a file or the flags left out with their field's and optimiser's own
    defaults (written into config.toml like any other value)."""
    field = items.get("field", FitConfig.field)
    if field == "hashgrid" and items.get("init", FitConfig.init) == "hull":
        for k, v in HASHGRID_HULL_DEFAULTS.items():
            items.setdefault(k, v)
    if items.get("optimizer") == "line-search":
        steps = HASHGRID_LINE_SEARCH_ITERATIONS if field == "hashgrid" else LINE_SEARCH_ITERATIONS
        items.setdefault("iterations", steps)
        # a step is a move that the held-out views must confirm: each one is validated
        items.setdefault("validate_every", 1)
        items.setdefault("patience", LINE_SEARCH_PATIENCE)
        hull = items.get("init", FitConfig.init) == "hull"
        if field == "hashgrid" and hull and items.get("adjoint") != "discrete":
            # the level set it follows skips (the grid's own rays never do): exact in
            # float64, and the quick drop's fit took 1,203 s instead of 1,497
            items.setdefault("skip_empty", True)


def interface_step_scale(index: float) -> float:
    """Factor on the default tracer step across a surface of glass up to this index: 1 up
    to 1.5, below in proportion to the index contrast above it, so that a ray bends as much
    per step (at 1.9 a quarter of a 1 mm interface made the truth's loss lowest at index
    1.8, an eighth at 1.9)."""
    return min(1.0, 0.5 / max(index - 1.0, 1e-6))


def load_config(path: Path | None, overrides: dict) -> FitConfig:
    """Defaults, then the TOML file, then command-line overrides (None values ignored)."""
    cfg = FitConfig()
    known = {f.name: f for f in fields(FitConfig)}
    items: dict = {}
    if path is not None:
        try:
            items.update(tomllib.loads(Path(path).read_text()))
        except FileNotFoundError:
            raise ClrefractError(f"{path}: config file not found") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ClrefractError(f"{path}: not valid TOML ({exc})") from None
    items.update({k: v for k, v in overrides.items() if v is not None})
    _field_defaults(items)
    for k, v in items.items():
        if k not in known:
            raise ClrefractError(f"unknown config key {k!r} (known: {', '.join(known)})")
        default = getattr(cfg, k)
        try:
            if isinstance(default, tuple):  # a string or a number is one value, not letters
                v = (v,) if isinstance(v, str | int | float) else tuple(v)
            else:
                v = type(default)(v)
        except (TypeError, ValueError):
            raise ClrefractError(f"config key {k!r}: cannot use {v!r}") from None
        setattr(cfg, k, v)
    cfg.validate()
    return cfg


def _toml(cfg: FitConfig) -> str:
    lines = []
    for k, v in asdict(cfg).items():
        if isinstance(v, str):
            lines.append(f'{k} = "{v}"')
        elif isinstance(v, bool):
            lines.append(f"{k} = {str(v).lower()}")
        elif isinstance(v, tuple | list):
            lines.append(f"{k} = [{', '.join(repr(x) for x in v)}]")
        else:
            lines.append(f"{k} = {v!r}")
    return "\n".join(lines) + "\n"


def resolution_at(cfg: FitConfig, it: int) -> int:
    """Grid resolution of a voxel fit at an iteration: the schedule splits the first half."""
    sched = [r for r in cfg.res_schedule if r < cfg.res]
    if not sched:
        return cfg.res
    span = cfg.iterations / 2 / len(sched)
    k = int(it // span)
    return sched[k] if k < len(sched) else cfg.res


def blur_at(cfg: FitConfig, it: int) -> float:
    frac = it / max(cfg.iterations * cfg.blur_until, 1)
    return cfg.env_blur * max(0.0, 1.0 - frac)


def block_at(cfg: FitConfig, it: int) -> int:
    """Side of the pixel blocks compared at iteration it: cfg.block halved in equal stages
    down to 1 by block_until of the iterations."""
    if cfg.block <= 1:
        return 1
    stages = int(math.log2(cfg.block)) + 1
    frac = it / max(cfg.iterations * cfg.block_until, 1)
    return max(1, cfg.block >> min(int(frac * stages), stages))


def batch_indices(
    cfg: FitConfig, it: int, pool: np.ndarray, marked: np.ndarray | None = None
) -> np.ndarray:
    """Training rays of an iteration, from `pool`: a share from `marked` (the masks' rays in
    the pool), the rest from all of it."""
    rng = np.random.default_rng([cfg.seed, it])
    size = min(cfg.batch, len(pool))
    if marked is None or len(marked) < 16 or cfg.mask_share <= 0:
        return pool[rng.integers(0, len(pool), size=size)]
    k = int(round(size * min(cfg.mask_share, 1.0)))
    return np.concatenate(
        [marked[rng.integers(0, len(marked), size=k)], pool[rng.integers(0, len(pool), size - k)]]
    )


def held_out_views(cfg: FitConfig, n_views: int) -> list[int]:
    """Training views kept for validation: every k-th, or none with too few views."""
    count = min(cfg.val_views, n_views // 5)
    if count <= 0:
        return []
    return list(range(n_views // count // 2, n_views, n_views // count))[:count]


def voxel_step(box, res: int) -> float:
    """A voxel fit's default step: half a cell of its final grid. The truth sampled on the
    grid (luneburg, plume, sphere; 16^3 to 128^3 over 100 mm) renders the test views within
    0.04 dB of a quarter cell's PSNR at half a cell; 1 mm loses 0.33 to 0.44 dB on the
    sphere at 96^3 and 128^3 and a whole cell up to 0.25 dB, while at 16^3 and 32^3 half a
    cell takes 0.3 to 0.6 times 1 mm's steps (tools/bench_voxel_step.py)."""
    return 0.5 * float(np.min(box.size)) / (res - 1)


def make_field(cfg: FitConfig, box, eta_max: float, res: int):
    """A fresh field of the configured kind (eta = 1 everywhere)."""
    if cfg.field == "levelset":
        from .fields.levelset import LevelSetField

        far = np.full((res, res, res), 4.0 * cfg.width)  # no surface: air everywhere
        return LevelSetField(far, box, eta=1.0, width=cfg.width, eta_max=eta_max)
    if cfg.field == "voxel":
        from .fields.voxel import VoxelGrid

        return VoxelGrid(np.ones((res, res, res)), box, interp=cfg.interp, eta_max=eta_max)
    from .fields.hashgrid import HashGridField

    return HashGridField(hashgrid_config(cfg, eta_max), box, seed=cfg.seed)


def hashgrid_config(cfg: FitConfig, eta_max: float = 1.6):
    """The hash grid a fit configuration describes."""
    from .fields.hashgrid import HashGridConfig

    return HashGridConfig(
        levels=cfg.levels,
        features=cfg.features,
        log2_table=cfg.log2_table,
        n_min=cfg.n_min,
        n_max=cfg.n_max,
        hidden=cfg.hidden,
        layers=cfg.layers,
        eta_max=eta_max,
        output=cfg.hashgrid_output,
    )


# fit_to_field scores a solid's fit at every RMS_EVERY-th of its points: 100,000 give its RMS
# to 1% (a sphere, 300 and 2,000 steps), and a refit after each line-search step spent a
# tenth of its time on it
RMS_EVERY = 4


def fit_to_field(
    field,
    source,
    width: float,
    iterations: int,
    seed: int = 0,
    surface: bool = True,
    rate: float = 1.0,
    stream=None,
    device=None,
    batch: int = 8192,
) -> float:
    """Fit a hash grid to another field at points of its box: uniform ones, and as many
    again around the interfaces, jittered by half the interface `width`. A solid with a
    signed distance (`source.sdf`: a level set, a scene's truth) is fitted as its surface
    (`fit_surface`) unless `surface` is False, any other field by its eta and gradient.
    Returns the RMS error of eta against the source (a solid's at a quarter of the points);
    `rate` scales the distillation's Adam rates (a refit from where the field is wants less
    than a start). With a `stream` it shows its progress there (a start's distillation takes
    minutes). `device`: (runtime, precision) runs it there (HashGridField._distil); `batch`
    points a step."""
    rng = np.random.default_rng([seed, 3])
    lo, size = np.asarray(field.box.lo), field.box.size
    solid = surface and hasattr(source, "sdf")
    if not solid and field.config.output == "ramp":
        raise ClrefractError(
            "a hash grid with the ramp output is fitted to a solid's signed distance, and "
            f"this {type(source).__name__} has none: use output = 'sigmoid'"
        )
    sample = source.sdf if solid else source.eval  # (phi, grad phi) or (eta, grad eta)
    pts = lo + rng.uniform(size=(200_000, 3)) * size
    value, grad = sample(pts)
    near = np.abs(value) < 2 * width if solid else np.linalg.norm(grad, axis=1) > 1e-3
    band = pts[near]
    if len(band):
        jitter = rng.normal(scale=width / 2, size=(200_000, 3))
        more = np.clip(band[rng.integers(0, len(band), 200_000)] + jitter, lo, lo + size)
        value_more, grad_more = sample(more)
        pts = np.concatenate([pts, more])
        value, grad = np.concatenate([value, value_more]), np.concatenate([grad, grad_more])
    bar = Progress(iterations, "distil", stream=stream) if stream is not None else None
    if solid:
        field.fit_surface(
            pts,
            value,
            grad,
            source.eta,
            width,
            iterations,
            batch=batch,
            seed=seed,
            rate=rate,
            progress=bar,
            device=device,
        )
        check = pts[::RMS_EVERY]
        return field.eta_rms(check, source.eval(check)[0], device)
    return field.fit_values(
        pts,
        value,
        grad,
        scale=width,
        iterations=iterations,
        batch=batch,
        seed=seed,
        progress=bar,
        device=device,
    )


class Fit(HullStart):
    """One fitting run on one dataset, in one run folder."""

    def __init__(self, dataset: Path, out: Path, cfg: FitConfig, stream=None):
        from .parallel import device_for
        from .runtime import Runtime

        self.ds = Dataset(dataset, box=box_of(cfg.box) if cfg.box else None)
        self.out, self.cfg = Path(out), cfg
        self.stream = stream or sys.stderr
        self.runtime = Runtime(device_for(cfg.device), queues=cfg.queues)
        self.box = self.ds.box
        if cfg.field == "voxel":
            self._size_from_images()
        if cfg.field == "voxel" and cfg.step == 0:
            cfg.step = voxel_step(self.box, cfg.res)  # recorded in config.toml
        self.eta_max = cfg.eta_max or self.ds.scene.eta_range[1] * 1.05
        self.origins, self.dirs, self.rgb = self.ds.rays_and_pixels("train")
        # rays of each training view, in order; held-out views serve validation only
        sizes = [cam.width * cam.height for cam in self.ds.train]
        view = np.repeat(np.arange(len(sizes)), sizes)
        held = np.isin(view, held_out_views(cfg, len(sizes)))
        self._pool, self._held = np.flatnonzero(~held), np.flatnonzero(held)
        self._view_of = view
        self._view_start = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        self._view_shape = np.array([(cam.height, cam.width) for cam in self.ds.train])
        self.weights = self.ds.pixel_weights("train")  # 0 where a photograph clipped
        self._env_full = self.ds.envmap()
        self._env_cache: dict[float, tuple] = {}
        self.it = 0
        self._masks = None
        self._marked = None
        self._marked_in_pool = None
        self._val_idx = None
        self._hulls: dict = {}
        self._free = None
        self.init_info: dict = {}
        self.best: tuple[float, int, np.ndarray | None] = (np.inf, 0, None)  # loss, it, params
        self.best_eta_max = None  # a hash grid's eta_max there (its guide's index moves)
        self.field = None
        self.engine = None
        self.guide = None  # a hash grid's line search: the level set it follows
        self.final_refit = None  # and its grid's one refit to the best step (refit = "best")
        self.size_search = None  # what the size and index search did (size_search.py)
        self.narrowing = None  # a narrowed run's finish against its earlier width (narrowing.py)
        self._search_bar = None  # the start search's progress, while it runs
        self._losses = None  # the start search's losses (start_losses.py)
        self._search_at = ""  # the shape and smoothing the search is at (their key)
        self._best_seen = np.inf
        self.adam = None
        self.params = None
        self.stopped: dict | None = None  # why a diverged run stopped (results.json)
        self.patience_stop: dict | None = None  # where `patience` ended the run
        self._occ = None
        self._val_tracer = None  # a hash grid's line search: validation that skips
        if cfg.skip_empty:
            from .fit_occupancy import TrainingOccupancy

            self._occ = TrainingOccupancy(
                cfg.skipping_field(), cfg.occupancy_res, cfg.occupancy_every, cfg.lr_phi
            )

    # --- field and optimiser -------------------------------------------------------------
    def _size_from_images(self) -> None:
        """Resolve res = 0 / n_max = 0 for the current box: one cell per pixel footprint."""
        from .limits import check_grid
        from .resolution import cells_for, pixel_footprint_mm

        auto = [n for n in ("res", "n_max") if getattr(self.cfg, n) == 0]
        if not auto:
            return
        foot = pixel_footprint_mm(self.ds.train, np.add(self.box.lo, self.box.hi) / 2)
        cells = cells_for(float(np.max(self.box.size)), foot)
        for name in auto:
            setattr(self.cfg, name, cells)
        if self.cfg.field in GRID_FIELDS:
            check_grid("res", self.cfg.res)
        self.stream.write(
            f"field: {cells} cells across the {np.max(self.box.size):.0f} mm box, one per "
            f"pixel footprint at the object ({foot:.2f} mm)\n"
        )

    def _make_field(self, res: int):
        return make_field(self.cfg, self.box, self.eta_max, res)

    def _bind(self, field, step: float = 0.0) -> None:
        self.field = field
        self.params = np.array(field.data(), np.float64)
        self.engine = self._engine_for(field, step)
        self._update_free()
        self._upload()

    def _engine_for(self, field, step: float = 0.0):
        from .gradient import GradientEngine
        from .parallel import shard

        engine = GradientEngine(
            field,
            self.box,
            step=step or self.cfg.step_mm,
            precision=self.cfg.precision,
            lanes=self.cfg.lanes or None,
            runtime=self.runtime,
            queues=self.cfg.queues,
            loss_space=self.cfg.loss,
            checkpoint_every=self.cfg.backward_checkpoints,
            growth_max=self.cfg.adjoint_growth_max,
            adjoint=self.cfg.adjoint,
            skip_empty=self.cfg.skip_empty and field.kind == self.cfg.skipping_field(),
            occupancy_res=self.cfg.occupancy_res,
        )
        return shard(engine, self.cfg.chunks)  # split over MPI ranks, if any

    def _upload(self, stepped: bool = False) -> None:
        """Send the parameters to the device; with skip_empty, rebuild the occupancy: always
        after a jump of the parameters (a start, a resume), when due after a training step."""
        tracer = self.engine.tracer
        tracer.upload_field()
        if self._occ is not None and tracer.skip_empty:
            self._occ.update(self.it, self.field, tracer, self._free, force=not stepped)

    def _groups(self):
        return self.field.param_groups(
            lr=self.cfg.lr,
            lr_table=self.cfg.lr_table,
            lr_mlp=self.cfg.lr_mlp,
            lr_phi=self.cfg.lr_phi,
            lr_index=self.cfg.lr_index,
        )

    def start(self) -> None:
        res = self.start_grid()
        if self.cfg.field == "hashgrid" and self._hull_fit():
            self._start_hashgrid(res)
        else:
            self._bind(self._make_field(res))
            if self._hull_fit():
                self._fill_hull()
        self.adam = Adam(len(self.params), self._groups())

    def start_grid(self) -> int:
        """The tracing step, box and grid resolution of the start, before any field is made
        (the resolution returned)."""
        cfg = self.cfg
        if cfg.field in ("levelset", "hashgrid") and cfg.step == 0:
            scale = interface_step_scale(self.ds.scene.eta_range[1])
            if scale < 1:  # recorded in config.toml, which render, eval and resume read
                cfg.step = cfg.step_mm * scale
        if cfg.field == "levelset" or (cfg.field == "hashgrid" and self._hull_fit()):
            self.box = self._object_box()
        self._size_from_images()
        return resolution_at(cfg, 0)

    def _start_hashgrid(self, res: int) -> None:
        """A hash grid starts as the level-set start (hull, index and offset searched the
        same way), fitted to its eta at points of the box: it starts where a level set does,
        as its output bias alone would take thousands of steps to reach glass."""
        guide_cfg = self.guide_config()
        self._bind(make_field(guide_cfg, self.box, self.eta_max, res), step=guide_cfg.step)
        self._fill_hull()
        if self.cfg.optimizer == "line-search":
            from .fit_linesearch import Guide

            self.guide = Guide(self.field, self.engine, self.params, self.eta_max)
        if not self.cfg.eta_max:
            self.eta_max = self.cfg.hashgrid_eta_max(self.init_info["eta"])
        rms = self.start_from(self.field)
        self.init_info["distilled_rms"] = rms
        self.stream.write(f"start: hash grid fitted to the level-set start (eta RMS {rms:.4f})\n")
        (self.out / "init.json").write_text(json.dumps(self.init_info, indent=2))

    def guide_config(self) -> FitConfig:
        """The level set a hash grid starts from, and that its line search follows: the
        fit's settings with a level set's own step at this dataset's index."""
        from dataclasses import replace

        cfg = replace(self.cfg, field="levelset", step=0.0)
        cfg.step = cfg.step_mm * interface_step_scale(self.ds.scene.eta_range[1])
        return cfg

    def start_from(self, source) -> float:
        """Start the hash grid as another field (`source.eval`) fitted into it, in the
        current box; returns the RMS error of eta."""
        field = self._make_field(0)
        rms = fit_to_field(
            field,
            source,
            self.cfg.width,
            self.cfg.distil_iterations,
            self.cfg.seed,
            stream=self.stream,
            device=self.distil_device(),
        )
        self._bind(field)
        return rms

    def distil_device(self):
        """Where a hash grid is fitted to another field (`distil_on`): fit_to_field's
        `device`."""
        return (self.runtime, self.cfg.precision) if self.cfg.distil_on == "device" else None

    def _maybe_regrid(self) -> None:
        if self.cfg.field != "voxel":
            return
        res = resolution_at(self.cfg, self.it)
        if res == self.field.values.shape[0]:
            return
        # upsample eta and the Adam moments (Teh et al.); step counts carry over
        old = self.field
        m = old.resampled_values(self.adam.m.reshape(old.values.shape), res)
        v = np.maximum(old.resampled_values(self.adam.v.reshape(old.values.shape), res), 0)
        t = int(self.adam.t.max())
        self._bind(old.resampled(res))
        self.adam = Adam(len(self.params), self._groups())
        self.adam.m, self.adam.v = m.ravel(), v.ravel()
        self.adam.t[:] = t

    def env_at(self, it: int):
        return self._blurred(it)[0]

    def targets_at(self, it: int) -> np.ndarray:
        return self._blurred(it)[1]

    def _blurred(self, it: int):
        """Environment and training images blurred alike: sigma pixels of the environment
        is the same angle in every image (exact where rays go straight), so early
        iterations compare coarse versions of both and the loss is smooth in eta."""
        sigma = round(blur_at(self.cfg, it), 1)
        hit = self._env_cache.get(sigma)
        if hit is None:
            if sigma <= 0:
                hit = (self._env_full, self.rgb)
            else:
                from scipy.ndimage import gaussian_filter

                env = self._env_full.blurred(sigma)
                angle = sigma * 2 * np.pi / self._env_full.width
                imgs = []
                start = 0
                for cam in self.ds.train:
                    n = cam.width * cam.height
                    px = 2 * math.atan(cam.height / (2 * cam.fl_y)) / cam.height
                    img = self.rgb[start : start + n].reshape(cam.height, cam.width, 3)
                    imgs.append(
                        gaussian_filter(img, (angle / px, angle / px, 0), mode="nearest").reshape(
                            -1, 3
                        )
                    )
                    start += n
                hit = (env, np.concatenate(imgs))
            self._env_cache = {sigma: hit}
        return hit

    # --- checkpoints -----------------------------------------------------------------------
    @property
    def checkpoint_path(self) -> Path:
        return self.out / "checkpoint.npz"

    def save_checkpoint(self) -> None:
        shape = np.array(self.field.values.shape if self.cfg.field in GRID_FIELDS else [0])
        with atomic_path(self.checkpoint_path, suffix=".npz") as tmp:
            best_loss, best_it, best_params = self.best
            np.savez(
                tmp,
                params=self.params,
                iteration=self.it,
                shape=shape,
                best_loss=best_loss,
                best_iteration=best_it,
                best_params=self.params if best_params is None else best_params,
                eta_max=self.eta_max,
                best_eta_max=self.best_eta_max or self.eta_max,
                **self.adam.state(),
                **(self.guide.state() if self.guide is not None else {}),
            )

    def load_checkpoint(self) -> None:
        path = self.checkpoint_path
        try:
            with np.load(path) as z:
                params, it, shape = z["params"], int(z["iteration"]), z["shape"]
                state = {k: z[k] for k in ("adam_m", "adam_v", "adam_t")}
                best = (float(z["best_loss"]), int(z["best_iteration"]), z["best_params"])
                guide = {k: z[k] for k in z.files if k.startswith("guide_")}
                tops = [float(z[k]) if k in z.files else None for k in ("eta_max", "best_eta_max")]
        except FileNotFoundError:
            raise ClrefractError(f"{path}: no checkpoint to resume from") from None
        except Exception as exc:  # noqa: BLE001 - any damage is the user's to know about
            raise ClrefractError(f"{path}: cannot read checkpoint ({exc})") from None
        res = int(shape[0]) if self.cfg.field in GRID_FIELDS else 0
        self.box, eta_max = _run_meta(self.out)
        self.eta_max = float(tops[0] or eta_max or self.eta_max)
        self.best_eta_max = tops[1]
        self._bind(self._make_field(res) if res else self._make_field(0))
        if len(params) != len(self.params):
            raise ClrefractError(
                f"{path}: checkpoint has {len(params)} parameters, the "
                f"configured field has {len(self.params)}"
            )
        self.params[:] = params
        self.field.set_data(self.params)
        self._upload()
        self.adam = Adam(len(self.params), self._groups())
        self.adam.load_state(state)
        self.it = it
        self.best = best if np.isfinite(best[0]) else (np.inf, 0, None)
        if self.cfg.field == "hashgrid" and self.cfg.optimizer == "line-search":
            from .fit_linesearch import Guide

            self.guide = Guide.restore(self, guide, path)

    # --- the loop ----------------------------------------------------------------------------
    def _marked_rays(self) -> np.ndarray:
        """Training rays the masks (grown by 2 pixels) mark."""
        from scipy.ndimage import binary_dilation

        if self._marked is None:
            self._marked = np.flatnonzero(
                np.concatenate(
                    [binary_dilation(m, iterations=2).ravel() for m in self._refraction_masks()]
                )
            )
        return self._marked

    def _marked_pool(self) -> np.ndarray:
        """The marked rays that gradients may use (not the held-out views')."""
        if self._marked_in_pool is None:
            self._marked_in_pool = np.intersect1d(
                self._marked_rays(), self._pool, assume_unique=True
            )
        return self._marked_in_pool

    def _mask_batch(self, tag: int, size: int = 0) -> np.ndarray:
        """A fixed batch (of `size`, 0: the configured batch) of the training rays that the
        masks (grown by 2 pixels) mark: only they can see the object, so they carry the
        whole signal of a start search."""
        marked = self._marked_pool()
        if len(marked) < 16:
            return self._fixed_batch(tag)
        rng = np.random.default_rng([self.cfg.seed, tag])
        return rng.choice(marked, size=min(size or self.cfg.batch, len(marked)), replace=False)

    def _fixed_batch(self, tag: int) -> np.ndarray:
        """A batch of training rays that depends only on (seed, tag)."""
        rng = np.random.default_rng([self.cfg.seed, tag])
        return self._pool[
            rng.integers(0, len(self._pool), size=min(self.cfg.batch, len(self._pool)))
        ]

    def _forward_loss(self, idx: np.ndarray, tracer=None) -> float:
        """Loss of the current field on training rays idx, against the sharp environment
        (forward pass only), traced by its engine's tracer or `tracer`."""
        return self.forward_render(idx, tracer)[0]

    def forward_render(self, idx: np.ndarray, tracer=None) -> tuple[float, np.ndarray]:
        """_forward_loss and the radiance of each ray (linear RGB, black where trapped)."""
        from .gradient import traced_loss

        r = (tracer or self.engine.tracer).trace(self.origins[idx], self.dirs[idx])
        loss, _, radiance = traced_loss(
            self._env_full, r.status, r.direction, self.rgb[idx], self.weights[idx], self.cfg.loss
        )
        return loss, radiance

    def validation_loss(self) -> float:
        """Loss on a fixed batch of the held-out views' rays, most through their masks
        (elsewhere every field near the hull renders alike); on training rays without
        held-out views. Of the guide's level set where that is what the held-out views judge
        (`validates_guide`)."""
        if self.validates_guide():
            from .fit_linesearch import on_guide

            with on_guide(self):
                return self.held_out_loss()
        return self.held_out_loss(self._validation_tracer())

    def validates_guide(self) -> bool:
        """A hash grid's line search that fits the grid to its best step alone (refit =
        "best"): its steps, their validation and its checkpoints are the level set's."""
        return self.guide is not None and self.cfg.refit == "best"

    def held_out_loss(self, tracer=None) -> float:
        """validation_loss of the fit's field, traced by its engine's tracer or `tracer`."""
        if len(self._held) == 0:
            return self._forward_loss(self._fixed_batch(11), tracer)
        if self._val_idx is None:
            rng = np.random.default_rng([self.cfg.seed, 11])
            marked = np.intersect1d(self._marked_rays(), self._held, assume_unique=True)
            size = min(self.cfg.batch, len(self._held))
            k = min(len(marked), size * 3 // 4)
            self._val_idx = np.concatenate(
                [rng.choice(marked, k, replace=False), rng.choice(self._held, size - k)]
            )
        return self._forward_loss(self._val_idx, tracer)

    def _validation_tracer(self):
        """With skip_empty, a hash grid's line search validates the grid through rays that
        skip the cells where its eta is constant, sampled from the grid as it is now (it
        changes between validations only by a refit), and steps as its engine does.
        Forward only, so no gradient is lost; its engine's own rays never skip. On the
        quick sphere: 4.2 s instead of 9.2, and 1.7 s to sample the grid."""
        if not (self.cfg.skip_empty and self.guide is not None):
            return None
        tracer = self._val_tracer
        if tracer is None or tracer.field is not self.field:
            from .render import run_tracer

            tracer = run_tracer(self.field, self.box, self.cfg, self.runtime, False)
            self._val_tracer = tracer
            return tracer
        tracer.upload_field()
        tracer.set_occupancy(tracer.field_occupancy())
        return tracer

    def _track_best(self) -> float | None:
        every = self.cfg.validate_every
        if every <= 0 or (self.it % every and self.it != self.cfg.iterations):
            return None
        if self.cfg.field in GRID_FIELDS and self.field.values.shape[0] != self.cfg.res:
            return None  # earlier grids are not candidates
        loss = self.validation_loss()
        if loss < self.best[0]:
            kept = self.guide.params if self.validates_guide() else self.params
            self.best = (loss, self.it, kept.copy())
            self.best_eta_max = self.eta_max
        return loss

    def use_best(self) -> None:
        """Load the parameters that scored best on the validation batch (a guide's: the
        grid fitted to them)."""
        searched = None
        if self.cfg.optimizer == "line-search" and self.cfg.size_search:
            from .size_search import size_index_search

            searched = self.size_search = size_index_search(self)
        if self.validates_guide():
            from .fit_linesearch import refit_to_best

            self.final_refit = refit_to_best(self, moved=bool(searched and searched["kept"]))
            return
        _, _, params = self.best
        if params is not None and len(params) == len(self.params):
            self.params[:] = params
            self.field.set_data(self.params)
            self.set_eta_max(self.best_eta_max or self.eta_max)

    def set_eta_max(self, eta_max: float) -> None:
        """A new top index (a hash grid's follows its guide's index), uploaded with the
        parameters; a level set's and a voxel grid's bound stays."""
        if self.cfg.field == "hashgrid" and eta_max != self.field.config.eta_max:
            from dataclasses import replace

            self.eta_max = float(eta_max)
            self.field.config = replace(self.field.config, eta_max=self.eta_max)
        self._upload()

    def _blocks(self, anchors: np.ndarray, side: int) -> np.ndarray:
        """The rays of side x side pixel blocks around the anchor rays, block after block
        (a block is kept inside its view)."""
        view = self._view_of[anchors]
        local = anchors - self._view_start[view]
        h, w = self._view_shape[view].T
        y0 = np.clip(local // w - side // 2, 0, np.maximum(h - side, 0))
        x0 = np.clip(local % w - side // 2, 0, np.maximum(w - side, 0))
        dy, dx = np.divmod(np.arange(side * side), side)
        rows = np.minimum(y0[:, None] + dy, h[:, None] - 1)
        cols = np.minimum(x0[:, None] + dx, w[:, None] - 1)
        return (self._view_start[view][:, None] + rows * w[:, None] + cols).ravel()

    def step(self) -> dict:
        if self.cfg.optimizer == "line-search":
            from .fit_linesearch import line_search_step

            return line_search_step(self)
        self._maybe_regrid()
        marked = self._marked_pool() if self.cfg.mask_share > 0 else None
        idx = batch_indices(self.cfg, self.it, self._pool, marked)
        side = block_at(self.cfg, self.it)
        if side > 1:  # whole blocks, as many as the batch holds (a multiple of the chunks)
            count = max(len(idx) // (side * side) // self.cfg.chunks, 1) * self.cfg.chunks
            idx = self._blocks(idx[:count], side)
        t0 = time.perf_counter()
        targets = self.targets_at(self.it)
        r = self.engine.loss_and_grad(
            self.origins[idx],
            self.dirs[idx],
            targets[idx],
            self.env_at(self.it),
            self.weights[idx],
            side * side,
        )
        reg, greg = self.field.regularizer(self.params)
        grad = r.grad + self.cfg.reg * greg
        if self.cfg.sparsity and self.cfg.field == "voxel":
            grad = grad + self.cfg.sparsity * (self.params > 1.0)
        if self._free is not None:
            grad[~self._free] = 0.0
        if not np.all(np.isfinite(grad)):
            raise FloatingPointError("non-finite gradient")
        decay = self.cfg.lr_final ** (self.it / self.cfg.iterations)
        before = self.params.copy()
        self.adam.step(self.params, grad, lr_scale=decay)
        if not np.all(np.isfinite(self.params)):
            self.params[:] = before  # the field stays as the iteration found it
            raise FloatingPointError("non-finite parameters")
        if self.cfg.field == "voxel":  # keep node values physical: 1 <= eta <= eta_max
            np.clip(self.params, 1.0, self.eta_max, out=self.params)
            if self._free is not None:
                self.params[~self._free] = 1.0
        self.field.set_data(self.params)
        self._upload(stepped=True)
        dt = time.perf_counter() - t0
        self.it += 1
        exited = r.status == 0
        cap = self.cfg.adjoint_growth_max
        return {
            "truncated": float(np.mean(r.growth[exited] > cap)) if cap > 0 else 0.0,
            "iteration": self.it,
            "loss": r.loss,
            "reg": float(reg),
            "psnr": psnr_linear_batch(r.radiance[exited], targets[idx][exited]),
            "rays_per_s": len(idx) / dt,
            "seconds": dt,
            "drift_mm": float(r.drift.max()),
            "blur": blur_at(self.cfg, self.it - 1),
            "block": side,
            "res": int(self.field.values.shape[0]) if self.cfg.field in GRID_FIELDS else 0,
            "steps_per_ray": r.steps / len(idx),
            **({"live": self._occ.live_fraction} if self._occ is not None else {}),
        }

    def run(self) -> dict:
        metrics_path = self.out / "metrics.jsonl"
        bar = Progress(self.cfg.iterations, "fit", unit="it", stream=self.stream)
        bar.done = self.it
        stop = _StopOnInterrupt()
        last_ckpt = self.it
        try:
            with metrics_path.open("a") as mf, stop:
                while self.it < self.cfg.iterations and not self._out_of_patience():
                    if stop.requested:
                        self.save_checkpoint()
                        raise ClrefractError(
                            f"interrupted at iteration {self.it}; checkpoint saved in "
                            f"{self.out}: continue with --resume"
                        )
                    if self.it == 0 and not np.isfinite(self.best[0]):
                        self._track_best()  # the start is a candidate too
                    m = self.step()
                    val = self._track_best()
                    if val is not None:
                        m["val_loss"] = val
                    mf.write(json.dumps(m) + "\n")
                    mf.flush()
                    blown = self._blown_up(val)
                    if blown:
                        return self._stop_diverged(blown, self.it)
                    bar.update(
                        1, loss=m["loss"], psnr=round(m["psnr"], 2), rays_s=int(m["rays_per_s"])
                    )
                    if self.it % self.cfg.checkpoint_every == 0:
                        self.save_checkpoint()
                        last_ckpt = self.it
        except KeyboardInterrupt:
            # a second Ctrl-C may have cut an update short: keep the last whole checkpoint
            raise ClrefractError(
                f"interrupted; the checkpoint of iteration {last_ckpt} in {self.out} is "
                "intact: continue with --resume"
            ) from None
        except FloatingPointError as exc:
            return self._stop_diverged(str(exc), self.it + 1)
        self.save_checkpoint()
        self.use_best()
        from .narrowing import judge_narrowing

        self.narrowing = judge_narrowing(self)  # may keep the earlier width's field.npz
        self.field.save(self.out / "field.npz")
        return self.finish()

    def _out_of_patience(self) -> bool:
        """Whether the last `patience` validated steps found no better held-out loss; says so
        once, and results.json records it."""
        waited = self.it - self.best[1]
        if not self.cfg.patience or not np.isfinite(self.best[0]):
            return False  # no validated step yet (or none asked for)
        if waited < self.cfg.patience * self.cfg.validate_every:
            return False
        self.patience_stop = {"at_iteration": self.it, "best_iteration": self.best[1]}
        self.stream.write(
            f"fit: no better held-out loss in the {waited} steps since step {self.best[1]}: "
            f"stopped (patience = {self.cfg.patience}; 0 runs every step)\n"
        )
        return True

    def finish(self) -> dict:
        from .report import write_fit_report

        return write_fit_report(self)

    def _blown_up(self, val: float | None) -> str:
        """Why the held-out loss says the fit diverged ("" if it does not)."""
        if val is None:
            return ""
        if not math.isfinite(val):
            return "non-finite held-out loss"
        best, factor = self.best[0], self.cfg.diverge_factor
        if factor and math.isfinite(best) and val > factor * best:
            return f"held-out loss {val:.4g} is {val / best:.1f}x its best {best:.4g}"
        return ""

    def _stop_diverged(self, reason: str, at: int):
        """End a diverged run with what it had before: the best validated parameters (else
        the last finite ones) as field.npz, the checkpoint rolled back to their iteration
        with fresh Adam moments (the old ones carry the blow-up), and results.json; then
        raise FitDiverged with one line saying why and what was kept."""
        _, best_it, best_params = self.best
        top = self.eta_max
        if best_params is not None and self.validates_guide():
            self.use_best()
            self.it, kept = best_it, "the best on held-out views"
            top = self.eta_max
        elif best_params is not None and len(best_params) == len(self.params):
            self.params[:] = best_params
            self.it, kept = best_it, "the best on held-out views"
            top = self.best_eta_max or top
        else:
            kept = "the last finite parameters"
        self.field.set_data(self.params)
        self.set_eta_max(top)
        self.adam = Adam(len(self.params), self._groups())
        self.stopped = {"reason": reason, "at_iteration": at, "field_iteration": self.it}
        self.save_checkpoint()
        self.field.save(self.out / "field.npz")
        result = self.finish()
        raise FitDiverged(
            f"fit diverged at iteration {at} ({reason}); {self.out} holds the field of "
            f"iteration {self.it} ({kept}) and its checkpoint: lower the learning rate in "
            f"{self.out / 'config.toml'} and --resume",
            result,
        )


class FitDiverged(ClrefractError):
    """A fit stopped because its numbers blew up; its run folder holds the last good state
    (field.npz, checkpoint.npz, results.json with "stopped")."""

    def __init__(self, message: str, result: dict):
        super().__init__(message)
        self.result = result


class _StopOnInterrupt:
    """Ctrl-C ends the run after the iteration in flight, so the checkpoint is consistent;
    a second Ctrl-C interrupts at once."""

    def __init__(self):
        self.requested = False
        self._old = None

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __enter__(self):
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._handler)
        return self

    def __exit__(self, *exc):
        import signal

        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
        return False


def _truncate_metrics(path: Path, iteration: int) -> None:
    """Drop metric lines past the checkpoint being resumed from."""
    if not path.is_file():
        return
    keep = [
        ln
        for ln in path.read_text().splitlines()
        if ln.strip() and json.loads(ln)["iteration"] <= iteration
    ]
    with atomic_path(path, suffix=".jsonl") as tmp:
        tmp.write_text("".join(ln + "\n" for ln in keep))


# what the start of a new run writes, removed again when the start fails
START_FILES = ("config.toml", "metrics.jsonl", "init.json", *RUN_FILES)


def extend_run(out: Path, iterations: int) -> None:
    """Give a line-search run more steps before it is resumed: its config.toml is the
    record of what it runs. Adam's rates decay over the run's whole length, so its length
    stays."""
    from dataclasses import replace

    cfg = load_config(out / "config.toml", {})
    if iterations == cfg.iterations:
        return
    if cfg.optimizer != "line-search":
        raise ClrefractError(
            f"{out}: --resume --iterations {iterations}: an Adam run's rates decay over its "
            f"{cfg.iterations} iterations; start a new run to train longer"
        )
    if iterations < cfg.iterations:
        raise ClrefractError(
            f"{out}: --resume --iterations {iterations}: the run has {cfg.iterations} steps, "
            "and --resume can only add steps"
        )
    _rewrite_config(out, replace(cfg, iterations=iterations))


def _rewrite_config(out: Path, cfg: FitConfig) -> None:
    # whole or not at all: under MPI the other ranks read it
    with atomic_path(out / "config.toml", suffix=".toml") as tmp:
        tmp.write_text(_toml(cfg))


def prepare_fit(dataset: Path, out: Path, cfg: FitConfig, resume: bool = False, stream=None) -> Fit:
    """A run ready to go: a new run folder with its field at the start, or a resumed one."""
    out = Path(out)
    if resume:
        if not (out / "config.toml").is_file():
            if start_losses.count(out):
                raise ClrefractError(
                    f"{out}: its start was interrupted before the run began; the same "
                    "command without --resume takes up the losses its search kept"
                )
            raise ClrefractError(f"{out}: no run to resume (config.toml missing)")
        cfg = load_config(out / "config.toml", {})
        ensure_out_dir(out, "run folder")
        fit = Fit(dataset, out, cfg, stream=stream)
        fit.load_checkpoint()
        _truncate_metrics(out / "metrics.jsonl", fit.it)
        return fit
    if any((out / name).exists() for name in RUN_FILES):
        raise ClrefractError(
            f"{out} already holds a run: use --resume to continue it, or another --out"
        )
    fresh_folder = not out.exists()
    ensure_out_dir(out, "run folder")
    had = {name for name in START_FILES if (out / name).exists()}
    try:
        return _start_run(dataset, out, cfg, stream)
    except BaseException:
        # a start that failed (or was interrupted) leaves no run behind, only its search's
        # losses, which the same command run again takes up
        for name in START_FILES:
            if name not in had:
                (out / name).unlink(missing_ok=True)
        kept = start_losses.count(out)
        if kept:
            (stream or sys.stderr).write(
                f"start: {kept} losses of its search kept in {out / start_losses.NAME}; "
                "the same command takes them up\n"
            )
        if fresh_folder and not any(out.iterdir()):
            out.rmdir()
        raise


def _start_run(dataset: Path, out: Path, cfg: FitConfig, stream) -> Fit:
    from .report import write_start_report

    fit = Fit(dataset, out, cfg, stream=stream)
    (out / "config.toml").write_text(_toml(cfg))
    (out / "metrics.jsonl").write_text("")
    t0 = time.perf_counter()
    fit.start()
    (out / "config.toml").write_text(_toml(fit.cfg))  # with what the start resolved
    write_start_report(fit, time.perf_counter() - t0)
    (out / "run.json").write_text(  # the field's box: a level set's is the object's
        json.dumps(
            {
                "dataset": str(Path(dataset).resolve()),
                "box": fit.box.to_dict(),
                "eta_max": fit.eta_max,
            },
            indent=2,
        )
    )
    fit.save_checkpoint()  # a run killed before its first step resumes from its start
    return fit


def _run_meta(run: Path):
    """The field's box and eta_max (None in runs that predate it) that run.json records."""
    from .fields.base import Box

    try:
        meta = json.loads((Path(run) / "run.json").read_text())
        return Box.from_dict(meta["box"]), meta.get("eta_max")
    except Exception as exc:  # noqa: BLE001 - any damage is the user's to know about
        raise ClrefractError(f"{run}: cannot read the run's box from run.json ({exc})") from None


def run_fit(dataset: Path, out: Path, cfg: FitConfig, resume: bool = False, stream=None) -> dict:
    from . import parallel

    if parallel.world().size > 1:  # under mpiexec: rank 0 alone writes the run folder
        return parallel.run_fit(dataset, out, cfg, resume, stream)
    return prepare_fit(dataset, out, cfg, resume, stream).run()


def field_from_run(run: Path):
    """The field of a run folder at its latest checkpoint (for rendering a run in progress):
    a hash grid's level set where the grid is fitted to it only at the end (refit = "best")."""
    from dataclasses import replace

    from .fields.base import Box

    run = Path(run)
    cfg = load_config(run / "config.toml", {})
    path = run / "checkpoint.npz"
    try:
        with np.load(path) as z:
            params, shape = z["params"], z["shape"]
            top = float(z["eta_max"]) if "eta_max" in z.files else None
            guide = {k: z[k] for k in z.files if k.startswith("guide_")}
        meta = json.loads((run / "run.json").read_text())
    except Exception as exc:  # noqa: BLE001 - any damage is the user's to know about
        raise ClrefractError(f"{run}: cannot read the run's checkpoint ({exc})") from None
    if guide and cfg.refit == "best":
        cfg, params = replace(cfg, field="levelset"), guide["guide_params"]
        top, shape = float(guide["guide_eta_max"]), [int(guide["guide_res"])]
    field = make_field(
        cfg,
        Box.from_dict(meta["box"]),
        top or meta["eta_max"],
        int(shape[0]) if cfg.field in GRID_FIELDS else 0,
    )
    field.set_data(params)
    return field
