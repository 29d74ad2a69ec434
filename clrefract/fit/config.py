"""A fit's configuration: `FitConfig`, its TOML, and the checks that need no field kind.

Defaults per field kind and optimiser, and the checks that depend on them, belong to the
field adapters (kinds.py) and `load_config` (configure.py).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import tomli_w

from ..dataset import box_values
from ..errors import ClrefractError
from ..limits import FIT_BYTES_PER_RAY, INT32_MAX, check_count, check_memory

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib


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
    # the hull: 0.5 unless told, as its optimizer and line_batch; kinds.HASHGRID_HULL_DEFAULTS)
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
    # polytope: its edges rounded over this many mm (a softened max over the faces); -1: the
    # start searches it (kinds.POLYTOPE_ROUNDINGS) and records what it chose
    rounding: float = -1.0
    # interface and polytope: the index inside the surface, "constant" or "quadratic" (a
    # graded interior, fields/interior.py, fitted with the surface from the start); "auto"
    # (field "auto" only, the command line's default there): the model choice tries the
    # chosen surface with a quadratic interior too (session.choose_model)
    interior: str = "constant"
    # a graded interior's frame, u = (x - centre) / scale: (cx, cy, cz, scale), mm; empty: the
    # start's solid's extent, recorded here so that resume, render and eval make the same field
    interior_frame: tuple = ()
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
    # a calibrated descent's ceiling: the rate it tried first, set by its calibration (0: the
    # rate does not grow back). A faint plume's calibrated rate was still its best at the end
    lr_max: float = 0.0
    # "adam", or "line-search" (level sets: each step keeps the rays whose adjoint grows at
    # most keep_growth, smooths the phi gradient over the grad_sigma scales (cells, each
    # weighted by its square) and takes the best of line_steps mm along it;
    # clrefract/fit/linesearch.py): from the quick sphere's start at 0.5 mm, 8 steps of
    # 60,000 rays took the test views from 31.98 to 33.59 dB. A hash grid from the hull
    # moves the level set it was distilled from that way, and is fitted to it (`refit`);
    # it is that fit's default
    optimizer: str = "adam"
    # "descent" (sharp interfaces): the phi gradient smoothed over descent_sigma mm, scaled so
    # that no node moves more than lr_phi mm, the index lr_index along its gradient's sign,
    # both decaying by a cosine to lr_final of the rates
    descent_sigma: float = 4.0
    # a second smoothing beside descent_sigma's, narrowing geometrically from it to this over
    # the first half of the iterations (0: none): coarse to fine, on the grid's own nodes
    descent_sigma_final: float = 0.0
    # a graded medium's descent: at most this many evaluations of L-BFGS on
    # quasi_newton_batches training batches drawn once, from its best grid, kept where the
    # held-out views prefer it (fit/quasi_newton.py; 0: none)
    quasi_newton: int = 0
    quasi_newton_batches: int = 12
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
    # (clrefract/fit/finishes.py), kept where the held-out views agree
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
    # rebuilt from the parameters, every occupancy_every iterations (clrefract/fit/occupancy.py: a
    # level set's band plus its drift, a voxel grid's free nodes). A hash grid's own rays
    # cannot skip; from the hull with the line search, the level set it follows (its start
    # search and its steps) does, by default (kinds.HashGridKind.defaults)
    skip_empty: bool = False
    occupancy_every: int = 25
    occupancy_res: int = 32
    precision: str = "float32"
    loss: str = "auto"
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
    # the panorama's rotation, each view's exposure and white balance and its camera's
    # rotation, fitted to the background pixels before the start (`dataset register-env`, kept
    # in the run folder): "auto" where the background differs from the panorama as the
    # dataset states it (calibrate.Mismatch), "on", or "off". A rendered capture with its
    # panorama turned by a few degrees and 0.3 EV of exposure jitter fitted at 17 dB unregistered
    register: str = "auto"
    # each training camera's centre fitted with the field (fit/centres.py): "fitted",
    # "recorded" (as the dataset states them), or "auto": fitted for a real capture (one the
    # fit registers, or one `dataset import` made), whose centres are never exact. The quick
    # sphere with centres recorded 0.2 mm off scored 33.3 dB on the true views, 37.8 fitted
    # (docs/design/capture-flaws.md)
    camera_centres: str = "auto"
    # a fitted centre's step, in pixels at the object: 0.018 did best of 0.0045 to 0.018 on
    # 25 views of 48 x 48 with centres 0.5 mm off
    lr_centres: float = 0.02

    def validate(self) -> None:
        """The checks every field kind shares (the kind's own: kinds.py)."""
        if self.box:
            self.box = tuple(box_values(self.box, "box"))
        frame = tuple(float(v) for v in self.interior_frame)
        if frame and not (len(frame) == 4 and all(map(math.isfinite, frame)) and frame[3] > 0):
            raise ClrefractError(
                f"interior_frame is a centre x y z and a scale > 0 (mm), got {list(frame)}"
            )
        self.interior_frame = frame
        check_count("batch", self.batch, 1, 2**26)
        check_memory(f"batch {self.batch}", self.batch * FIT_BYTES_PER_RAY * 4)
        check_count("iterations", self.iterations, 1, INT32_MAX)
        check_count("queues", self.queues, 1, 64)
        check_count("patience", self.patience, 0, INT32_MAX)
        for name in ("res", "n_max"):
            if getattr(self, name) < 0:
                raise ClrefractError(
                    f"{name} must be at least 1 (or 0: from the photographs), "
                    f"got {getattr(self, name)}"
                )
        if not (self.step >= 0 and math.isfinite(self.step)):
            raise ClrefractError(f"step must be positive (or 0: automatic), got {self.step}")
        if not (math.isfinite(self.rounding) and (self.rounding >= 0 or self.rounding == -1)):
            raise ClrefractError(
                f"rounding must be at least 0 mm (or -1: searched), got {self.rounding}"
            )
        if not (self.lr_centres > 0 and math.isfinite(self.lr_centres)):
            raise ClrefractError(
                f"lr_centres must be above 0 (pixels a step), got {self.lr_centres}"
            )
        if not (self.lr_max >= 0 and math.isfinite(self.lr_max)):
            raise ClrefractError(f"lr_max must be at least 0, got {self.lr_max}")
        for name in ("quasi_newton", "quasi_newton_batches"):
            if getattr(self, name) < 0:
                raise ClrefractError(f"{name} must be at least 0, got {getattr(self, name)}")
        for name in ("descent_sigma", "descent_sigma_final"):
            mm = getattr(self, name)
            if not (mm >= 0 and math.isfinite(mm)):
                raise ClrefractError(f"{name} must be at least 0 (mm), got {mm}")
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
        if self.init not in ("hull", "empty"):
            raise ClrefractError(f"init must be 'hull' or 'empty', got {self.init!r}")
        if self.adjoint not in ADJOINTS:
            raise ClrefractError(
                f"adjoint must be one of {', '.join(ADJOINTS)}, got {self.adjoint!r}"
            )
        if self.backward_checkpoints < 0:
            raise ClrefractError(
                f"backward_checkpoints must be >= 0, got {self.backward_checkpoints}"
            )
        if self.skip_empty:
            if self.adjoint == "discrete":
                raise ClrefractError(
                    "skip_empty needs adjoint = 'continuous': the discrete adjoint replays "
                    "every step"
                )
            if not 1 <= self.occupancy_res <= 1024:
                raise ClrefractError(f"occupancy_res must be 1 to 1024, got {self.occupancy_res}")
            if self.occupancy_every < 1:
                raise ClrefractError(
                    f"occupancy_every must be at least 1, got {self.occupancy_every}"
                )
        if self.optimizer not in OPTIMIZERS:
            raise ClrefractError(
                f"optimizer must be one of {', '.join(OPTIMIZERS)}, got {self.optimizer!r}"
            )
        if self.distil_on not in ("device", "host"):
            raise ClrefractError(f"distil_on must be 'device' or 'host', got {self.distil_on!r}")
        if self.interp not in ("smoothstep", "trilinear", "bspline"):
            raise ClrefractError(
                f"interp must be 'bspline', 'smoothstep' or 'trilinear', got {self.interp!r}"
            )


# each key's `clrefract fit --help` text (cli.py appends its default unless the text gives
# it, as where it depends on the field kind or the optimiser)
HELP = {
    "field": "auto (the command line's default): the start tries interface, polytope and voxel "
    "and keeps the one the held-out views prefer; voxel: eta on a grid (any medium); "
    "levelset: one index inside a sharp surface (glass, water) on a ramp of --width; "
    "hashgrid: hash grid + MLP; interface: one index inside a zero-width surface, traced by "
    "Snell's law at each crossing; polytope: one index inside flat faces (a prism, a cube, "
    "cut glass), the planes of the visual hull's faces moved by Adam",
    "res": "grid resolution (voxel values or level set); 0: one cell per pixel at the object",
    "res_schedule": "voxel grids: coarse-to-fine resolutions before --res, e.g. 16 32 (the "
    "hull start wants the final grid at once)",
    "interp": "voxel weights: C2 tricubic B-spline, C1 smoothstep or trilinear",
    "width": "interface width, mm; with --resume, a line-search run's new width, its size and "
    "index searched again there (default: 1.0; a hash grid from the hull 0.5)",
    "lr_phi": "learning rate of the level set's distance, mm per step",
    "lr_index": "learning rate of the index (a surface model's, and a graded interior's terms)",
    "levels": "hash grid levels",
    "features": "hash grid features per level",
    "log2_table": "hash table size, log2",
    "n_min": "hash grid's coarsest level resolution",
    "n_max": "hash grid's finest level resolution over the object's box; 0: one cell per "
    "pixel at the object",
    "hidden": "MLP width",
    "layers": "MLP hidden layers",
    "eta_max": "hash grid's highest index (0: the scene's upper eta bound, from the hull plus "
    "--index-headroom)",
    "output": "how the hash grid's MLP output becomes eta: ramp (a level set's C2 ramp, an "
    "interface) or sigmoid (smooth everywhere, for a start from empty space) (default: ramp "
    "from the hull, sigmoid from empty space)",
    "rounding": "polytope: mm over which its edges are rounded (a softened max over its faces); "
    "-1: searched by the start",
    "interior": "interface and polytope: the index inside the surface, constant or quadratic "
    "(graded-index glass: a quadratic of position, rays bent by the eikonal equation inside); "
    "auto (with field auto): the model choice tries the chosen surface with a quadratic "
    "interior too, and keeps it where the held-out views prefer it (default: auto with field "
    "auto, else constant)",
    "interior_frame": "a graded interior's frame: centre x y z and scale, mm (default: the "
    "start's solid's extent, recorded in config.toml)",
    "index_headroom": "a sigmoid hash grid from the hull starts with eta_max this far above "
    "the start's index, in units of index - 1",
    "distil_iterations": "steps fitting the hash grid to its level-set start",
    "distil_on": "where that fitting (and a line search's refits) runs: device (the fit's "
    "OpenCL device and precision) or host (float64 NumPy)",
    "iterations": "steps of the optimiser (default: 600 for Adam; a line search 16, a hash "
    "grid's 32)",
    "batch": "rays per iteration",
    "lr": "learning rate of voxel values (a level set's index); with descent, a voxel's "
    "largest move per step",
    "lr_table": "learning rate of hash tables",
    "lr_mlp": "learning rate of the MLP",
    "lr_final": "learning rates decay exponentially to this fraction",
    "lr_max": "descent: the rate a calibrated step grows back to, x1.5 at each validation "
    "that finds a better held-out loss (set by the calibration; 0: it does not grow)",
    "optimizer": "adam, or line-search (level sets, and hash grids from the hull through their "
    "level set: the rays whose adjoint stays tame, a smoothed shape gradient and the best of "
    "a few moves along it), or descent (interfaces and voxel grids: a smoothed, bounded step "
    "of the grid; hash grids follow a voxel grid's) (default: adam; a hash grid from the hull "
    "line-search, from empty space descent; an interface and a voxel grid descent)",
    "descent_sigma": "descent: the grid gradient's smoothing, mm",
    "descent_sigma_final": "descent: a second smoothing of the gradient, each its own step, "
    "narrowing geometrically from descent_sigma to this, mm (at least 1.25 cells), over the "
    "first half of the iterations (0: none)",
    "quasi_newton": "graded descent: at most this many evaluations of L-BFGS from its best "
    "grid on quasi_newton_batches training batches drawn once, in coordinates smoothed over "
    "octaves, kept where the held-out views prefer it (0: none; a voxel grid's descent and a "
    "hash grid's that follows one: 32)",
    "quasi_newton_batches": "graded descent: the quasi-Newton finish's rays, in batches",
    "keep_growth": "line search: keep the rays whose adjoint grows at most this factor",
    "grad_sigma": "line search: smooth the shape gradient over these scales, cells (each "
    "weighted by its square)",
    "line_steps": "line search: moves along the smoothed gradient tried each step, mm (the "
    "best is taken)",
    "index_steps": "line search: index moves tried after each shape move (none: the index "
    "stays the start's)",
    "refit_iterations": "steps of a hash grid's refit to the level set its line search moved",
    "refit": "hash grid line search: fit the grid to the best step once, at the end (best), "
    "or after every move taken, validating the grid (step)",
    "size_search": "after a line search, grow its best level set and move its index together, "
    "kept where the held-out views agree",
    "line_batch": "mask rays a line-search step takes (default: 0, the batch; a hash grid "
    "from the hull 32768)",
    "reg": "smoothness regulariser weight",
    "sparsity": "weight of an L1 pull of voxel values towards eta = 1 (empty space)",
    "init": "start from the visual hull of the refraction masks (a voxel grid's filled solid "
    "or graded from its surface, as the loss prefers) or eta = 1 (default: hull)",
    "mask_threshold": "sRGB difference from the straight view that marks a mask pixel",
    "free_cells": "cells around the hull where eta may change (-1: everywhere)",
    "hull_tolerance": "share of the views a hull point may lie outside",
    "hull_carve": "leave out of the hull a view whose mask carves more than this share of the "
    "other views' hull (0: keep every view)",
    "tighten_hull": "level sets: also try the hull tightened by silhouette-held curvature "
    "flow, kept if its loss is lower",
    "shell_starts": "level sets: also try the hull hollowed to shells 2, 4 and 6 cells deep "
    "(a bowl, a glass)",
    "mask_share": "share of each training batch drawn from the refraction masks (0: all "
    "pixels alike; a voxel grid 0.8); masks that mark under 1% of the pixels (a faint gas) "
    "mark no object and are not drawn from",
    "block": "compare training images by blocks of this many pixels a side at first, halving "
    "to single pixels by --block-until (0 or 1: pixels throughout)",
    "block_until": "fraction of the iterations by which the blocks reach single pixels",
    "env_blur": "initial environment blur, pixels, sharpened to 0 (the photographs are "
    "blurred by the same angle, exact for straight rays only: under a strong lens the "
    "blurred views prefer empty space)",
    "blur_until": "fraction of the iterations over which the blur goes to 0",
    "step": "integrator step, mm (default: 0, automatic: width/4 for level sets and hash "
    "grids, finer above index 1.5; half a cell of the final grid for voxel grids)",
    "backward_checkpoints": "forward states kept every this many steps for the backward pass "
    "(0: constant memory)",
    "adjoint_growth_max": "stop a ray's backward pass once its adjoint grew by this factor "
    "(0: never)",
    "adjoint": "backward pass: adjoint-state ODE (continuous) or the exact discrete adjoint "
    "of each step, replayed from checkpoints",
    "skip_empty": "rays fly straight through cells where eta cannot vary, forward and "
    "backward (level set, voxel, and a hash grid's level set from the hull; same gradient, "
    "less time where the object is small) (default: false; true for a voxel grid free near its "
    "hull, and a hash grid from the hull with the line search)",
    "occupancy_every": "with --skip-empty: rebuild the occupancy every this many iterations",
    "occupancy_res": "with --skip-empty: occupancy grid resolution over the box, per axis",
    "precision": "floating-point precision of the device kernels",
    "loss": "colour space of the loss: auto (srgb420 where every training frame is a JPEG "
    "with 4:2:0 chroma, else srgb); srgb (encoded and clipped, as the test metrics); "
    "srgb420: luma per pixel, chroma per 2 x 2 block (photographs stored as JPEG with 4:2:0 "
    "chroma subsampling, as phones and most cameras write them); linear radiance",
    "queues": "command queues the batch is split across",
    "lanes": "rays per work-item (0: the device's default)",
    "device": "OpenCL device: 'P:D' index or a name substring; under MPI a comma-separated "
    "list indexed by local rank (default: PYOPENCL_CTX, else the first GPU, else a CPU)",
    "chunks": "under MPI, each batch is cut into this many pieces (a power of two) summed in "
    "one fixed order: any number of ranks up to it gives the same gradient",
    "seed": "random seed (batches, the hash grid's start, the hull's tightening)",
    "checkpoint_every": "save a checkpoint every this many iterations",
    "validate_every": "held-out loss every this many iterations, the best parameters kept "
    "(0: never) (default: 25; a line search 1)",
    "patience": "stop once this many validated steps in a row find no better held-out loss "
    "(0: run every iteration) (default: 0; a line search 16)",
    "val_views": "hold every k-th training view out of the gradient for validation (0, or "
    "fewer than five training views each: validate on training rays)",
    "diverge_factor": "stop once the held-out loss exceeds its best by this factor, keeping "
    "the best field (0: never); a non-finite loss, gradient or parameter always stops",
    "test_views": "test views rendered at the end (-1: all)",
    "box": "the object's box in mm, instead of scene.json's or the cameras' (default: the "
    "dataset's)",
    "register": "fit the panorama's rotation, each view's exposure and white balance and its "
    "camera's rotation to the background pixels before the start, kept in the run folder "
    "(registration.json): auto where the background differs from the panorama as the dataset "
    "states it, on, or off (default: auto)",
    "camera_centres": "recorded: the training cameras stand where the dataset says; fitted: each "
    "one's centre moves in its image plane with the field, by the loss's gradient at its rays' "
    "origins (camera_centres.json in the run folder; held-out and test views keep theirs); "
    "auto: fitted for a real capture (one the fit registers, or one `dataset import` made) "
    "(default: auto)",
    "lr_centres": "a fitted camera centre's step, in pixel widths at the object (default: 0.02)",
}


ADJOINTS = ("continuous", "discrete")
OPTIMIZERS = ("adam", "line-search", "descent")
# keys of a fixed set of values, as `validate`, kinds.KINDS and configure.py check them
# ("" for output: ramp from the hull, sigmoid from empty space)
CHOICES = {
    "field": ("auto", "interface", "polytope", "voxel", "levelset", "hashgrid"),
    "interp": ("bspline", "smoothstep", "trilinear"),
    "output": ("ramp", "sigmoid"),
    "init": ("hull", "empty"),
    "distil_on": ("device", "host"),
    "optimizer": OPTIMIZERS,
    "refit": ("best", "step"),
    "adjoint": ADJOINTS,
    "precision": ("float32", "float64"),
    "loss": ("auto", "srgb", "srgb420", "linear"),
    "register": ("auto", "on", "off"),
    "interior": ("auto", "constant", "quadratic"),
    "camera_centres": ("auto", "recorded", "fitted"),
}
KNOWN = {f.name: f for f in fields(FitConfig)}


def check_choices(cfg: FitConfig) -> None:
    """A --config file's values of the CHOICES keys, refused as the flags' are (after the
    checks that name a key's choices their own way)."""
    for key, allowed in CHOICES.items():
        value = getattr(cfg, key)
        if value not in allowed and not (key == "output" and value == ""):
            raise ClrefractError(f"{key} must be one of {', '.join(allowed)}, got {value!r}")


def to_toml(cfg: FitConfig) -> str:
    """config.toml's text: every key, read back by `read_toml` to the same values."""
    return tomli_w.dumps(
        {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(cfg).items()}
    )


def read_toml(path: Path) -> dict:
    """The keys of a TOML file, as read (one line naming the file where it cannot be)."""
    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ClrefractError(f"{path}: config file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ClrefractError(f"{path}: not valid TOML ({exc})") from None


def coerced(items: dict) -> FitConfig:
    """A FitConfig of these keys, each turned into its default's type (unknown keys, and
    values of another kind, refused in one line)."""
    cfg = FitConfig()
    for k, v in items.items():
        if k not in KNOWN:
            raise ClrefractError(f"unknown config key {k!r} (known: {', '.join(KNOWN)})")
        setattr(cfg, k, _as_type_of(getattr(cfg, k), k, v))
    return cfg


def _as_type_of(default, key: str, v):
    bad = ClrefractError(f"config key {key!r}: cannot use {v!r}")
    if isinstance(default, bool):
        # bool("false") is True: a string says which it means
        words = {"true": True, "false": False}
        if isinstance(v, str) and v.lower() in words:
            return words[v.lower()]
        if isinstance(v, bool | int) and v in (0, 1):
            return bool(v)
        raise bad
    try:
        if isinstance(default, tuple):  # a string or a number is one value, not letters
            return (v,) if isinstance(v, str | int | float) else tuple(v)
        return type(default)(v)
    except (TypeError, ValueError):
        raise bad from None
