"""`Fit`: one fitting run's state on one dataset, in one run folder. Its parts decide: the
field kind's adapter (kinds.py), the training rays and objective, the start (starts.py),
the optimiser (optimizers.py) and the finish (finishes.py); the loop is loop.py's."""

from __future__ import annotations

import sys

import numpy as np

from ..calibrate import CENTRES_FILE, run_corrections
from ..dataset import Dataset, box_of
from ..errors import ClrefractError
from ..resolution import pixel_footprint_mm
from .binding import Bound, engine_for, forward_settings
from .centres import CameraCentres, centres_setting
from .config import FitConfig
from .kinds import interface_step_scale, kind_named, kind_of
from .loop import train
from .objective import Objective, loss_space
from .occupancy import TrainingOccupancy
from .optimizers import optimizer_for
from .rays import TrainingRays
from .runfolder import Best, Checkpoint, RunFolder
from .starts import STARTS, Hulls


class Fit:
    """One fitting run on one dataset, in one run folder."""

    def __init__(self, dataset, out, cfg: FitConfig, stream=None, folder: RunFolder | None = None):
        from ..parallel import device_for
        from ..runtime import Runtime

        self.ds = Dataset(dataset, box=box_of(cfg.box) if cfg.box else None)
        self.out = folder or RunFolder(out)
        corrections = run_corrections(self.out.path)  # registration.py's, where it registered
        if corrections is not None:
            corrections.apply(self.ds)
        self.cfg, self.kind = cfg, kind_of(cfg)
        self.stream = stream or sys.stderr
        self.runtime = Runtime(device_for(cfg.device), queues=cfg.queues)
        self.box = self.ds.box
        if self.kind.sized_early(cfg):
            self.size_from_images()
            if cfg.step == 0:
                cfg.step = self.kind.early_step(self.box, cfg)  # recorded in config.toml
        self.eta_max = cfg.eta_max or self.ds.scene.eta_range[1] * 1.05
        chosen = loss_space(cfg.loss, self.ds)
        if chosen != cfg.loss and chosen == "srgb420":
            self.stream.write(
                "loss: srgb420 (the frames are JPEGs with 4:2:0 chroma: luma per pixel, "
                "chroma per 2 x 2 block as the file stored it)\n"
            )
        cfg.loss = chosen  # recorded in config.toml
        if cfg.loss == "srgb420":  # the blocks' colour as stored, not the decoder's smear
            self.ds.train_chroma = "stored"
        self.rays = TrainingRays(self.ds, cfg)
        # settled where a run starts (session.py), else here; recorded in config.toml
        cfg.camera_centres = centres_setting(cfg, self.ds.scene, corrections is not None)
        centres = None
        if cfg.camera_centres == "fitted":
            centres = CameraCentres(
                self.ds.train,
                self.rays.view_of,
                self.rays.held,
                pixel_footprint_mm(self.ds.train, np.add(self.box.lo, self.box.hi) / 2),
                cfg.lr_centres,
                lambda it: cfg.lr_final ** (it / cfg.iterations),
            )
        self.objective = Objective(self.rays, cfg.loss, cfg.batch, cfg.seed, centres)
        self.hulls = Hulls(self.ds, cfg, self.rays)
        self.it = 0
        self.init_info: dict = {}
        self.best = Best()
        self.bound: Bound | None = None
        self.optimizer = None
        self.record: dict = {}  # what results.json reports beside the scores
        self.walls = None  # the box's walls the masks reach (box_walls.Walls), at the start
        self.occupancy = None
        if cfg.skip_empty:  # one rule, for the kind of field whose rays skip
            kind = kind_named(self.kind.skipping_kind(cfg))
            self.occupancy = TrainingOccupancy(
                kind, cfg.occupancy_res, cfg.occupancy_every, cfg.lr_phi
            )

    # --- the bound field ----------------------------------------------------------------------
    @property
    def field(self):
        return self.bound.field

    @property
    def params(self) -> np.ndarray:
        return self.bound.params

    @property
    def engine(self):
        return self.bound.engine

    def make_field(self, res: int):
        return self.kind.make(self.cfg, self.box, self.eta_max, res)

    def bound_for(self, field, step: float = 0.0, kind=None) -> Bound:
        """`field` with an engine of the fit's settings (`step` in place of its own) and,
        where its rays skip, the fit's occupancy; the nodes free to move are those of its
        `kind` (the fit's unless told: a guide's differs)."""
        kind = kind or self.kind
        engine = engine_for(field, self.box, self.cfg, self.runtime, step)
        skips = self.occupancy if engine.tracer.skip_empty else None
        free = None
        if kind.frees_near_hull(self.cfg):
            hull = self.hulls.at(self.box, kind.resolution(field))
            free = kind.free_nodes(self.cfg, hull)
        bound = Bound(field, engine, skips, free)
        bound.upload(self.it)
        return bound

    def guide_bound(self, field, cfg: FitConfig) -> Bound:
        """A guide's `field` (of `cfg`: guide_config's) bound as a run of its own kind binds
        it: its step, and the nodes its kind lets move."""
        kind = kind_named(cfg.field)
        step = kind.early_step(self.box, cfg) if kind.sized_early(cfg) else cfg.step
        return self.bound_for(field, step, kind=kind)

    def bind(self, field, step: float = 0.0) -> None:
        """Train `field` from here on."""
        self.bound = self.bound_for(field, step)

    def adopt(self, field, cfg: FitConfig) -> None:
        """Finish with another field and the settings it was fitted with (a narrowed run's
        earlier width)."""
        self.cfg = cfg
        self.bound = Bound(field, engine=None)  # saved and scored, never traced back

    def groups(self):
        """The field's parameter groups with the configured rates (Adam's)."""
        c = self.cfg
        return self.field.param_groups(
            lr=c.lr, lr_table=c.lr_table, lr_mlp=c.lr_mlp, lr_phi=c.lr_phi, lr_index=c.lr_index
        )

    def set_eta_max(self, eta_max: float) -> None:
        """A new top index (a hash grid's follows its guide's index), uploaded with the
        parameters; a level set's and a voxel grid's bound stays."""
        self.eta_max = float(eta_max)
        self.bound.with_top(self.cfg, self.eta_max, self.it)

    def use_best(self) -> None:
        """Load the parameters that scored best on the held-out views."""
        best = self.best
        if best.params is not None and len(best.params) == len(self.params):
            self.params[:] = best.params
            self.field.set_data(self.params)
            self.set_eta_max(best.eta_max or self.eta_max)

    def distil_device(self):
        """Where a hash grid is fitted to another field (`distil_on`): fit_to_field's
        `device`."""
        return (self.runtime, self.cfg.precision) if self.cfg.distil_on == "device" else None

    def forward_tracer(self, field, cfg: FitConfig | None = None, interface_steps: bool = True):
        """A forward tracer of `field` as a run of `cfg` (the fit's) traces it."""
        from ..render import run_tracer

        settings = forward_settings(cfg or self.cfg, interface_steps)
        return run_tracer(field, self.box, settings, self.runtime)

    def step(self) -> dict:
        """One step of the optimiser; its metrics row."""
        return self.optimizer.step(self)

    def run(self) -> dict:
        """Train to the end (loop.py); the results."""
        return train(self)

    # --- the start ----------------------------------------------------------------------------
    def size_from_images(self) -> None:
        """Resolve res = 0 / n_max = 0 for the current box: one cell per pixel footprint."""
        from ..limits import check_grid
        from ..resolution import cells_for

        auto = [n for n in ("res", "n_max") if getattr(self.cfg, n) == 0]
        if not auto:
            return
        foot = pixel_footprint_mm(self.ds.train, np.add(self.box.lo, self.box.hi) / 2)
        cells = cells_for(float(np.max(self.box.size)), foot)
        for name in auto:
            setattr(self.cfg, name, cells)
        if self.kind.grid:
            check_grid("res", self.cfg.res)
        self.stream.write(
            f"field: {cells} cells across the {np.max(self.box.size):.0f} mm box, one per "
            f"pixel footprint at the object ({foot:.2f} mm)\n"
        )

    def start_grid(self) -> int:
        """The tracing step, box and grid resolution of the start, before any field is made
        (the resolution returned)."""
        cfg = self.cfg
        if self.kind.interface and cfg.step == 0:
            scale = interface_step_scale(self.ds.scene.eta_range[1])
            if scale < 1:  # recorded in config.toml, which render, eval and resume read
                cfg.step = self.kind.step_mm(cfg) * scale
        if self.kind.object_box(cfg):
            self.box = self.hulls.object_box()
        self.size_from_images()
        return self.kind.resolution_at(cfg, 0)

    def check_walls(self, say: bool = True) -> None:
        """Find (and unless `say` is false, warn) where the masks' hull reaches the dataset's
        box's walls, where the field is held at 1 (box_walls), with the --box to give."""
        from ..box_walls import box_walls

        c = self.cfg
        self.walls = box_walls(
            self.ds.box, self.ds.train, self.rays.masks(), c.hull_tolerance, c.hull_carve
        )
        if self.walls is not None and say:
            self.stream.write(f"warning: {self.ds.root}: {self.walls.message()}\n")

    def start(self, say_walls: bool = True) -> None:
        """Start the field (starts.py); `say_walls`: warn where the medium reaches the box's
        walls (a model's later candidates find the same, said once)."""
        self.check_walls(say_walls)
        res = self.start_grid()
        guide = STARTS[self.kind.start(self.cfg)]().run(self, res)
        graded = self.kind.with_interior(self.cfg, self.field)  # a surface placed, then graded
        if graded is not self.field:
            self.bind(graded)
        self.optimizer = optimizer_for(self, guide)

    # --- validation ---------------------------------------------------------------------------
    def validation_loss(self) -> float:
        """The held-out loss of the field the optimiser has the held-out views judge."""
        return self.optimizer.validation_loss(self)

    def loss(self, idx: np.ndarray, tracer=None) -> float:
        """The loss of training rays idx through the fit's field (or `tracer`)."""
        return self.objective.loss(tracer or self.bound.tracer, idx)

    def held_out_loss(self, tracer=None) -> float:
        """The held-out loss of the fit's own field, traced by its engine or `tracer`."""
        return self.objective.held_out_loss(tracer or self.bound.tracer)

    def track_best(self) -> float | None:
        """The held-out loss where validation is due (None elsewhere); the best kept."""
        every = self.cfg.validate_every
        if every <= 0 or (self.it % every and self.it != self.cfg.iterations):
            return None
        if self.kind.grid and self.kind.resolution(self.field) != self.cfg.res:
            return None  # earlier grids are not candidates
        loss = self.validation_loss()
        if loss < self.best.loss:
            judged = self.optimizer.judged(self)
            self.best = Best(loss, self.it, judged.params.copy(), self.eta_max)
        return loss

    def write_centres(self) -> None:
        """camera_centres.json: where the fit moved each training camera (fitted centres)."""
        centres = self.objective.centres
        if centres is None or not self.out.writes:
            return
        train = {id(cam): f"{src.name}: frames[{k}]" for src, k, cam in self.ds.frames()}
        names = [(train[id(cam)], cam.file_path) for cam in self.ds.train]
        self.out.write_json(CENTRES_FILE, centres.report(names))

    def solve_centres(self) -> None:
        """Where due (CameraCentres.solve_due), each moving view's centre solved against the
        field as it stands (view_offsets.estimate_offsets)."""
        from ..log import Progress
        from ..view_offsets import PROGRESS_PER_VIEW, estimate_offsets

        centres = self.objective.centres
        if centres is None or not centres.solve_due(self.it, self.cfg.iterations):
            return
        views = centres.moving()
        total = len(views) * PROGRESS_PER_VIEW  # each view's set-up and rounds
        with Progress(total, "camera centres", unit="step", stream=self.stream) as bar:
            found = estimate_offsets(
                self.ds, self.bound.tracer, views, self.cfg.mask_threshold, centres.world(),
                progress=bar.update, env=self.rays.env, space=self.cfg.loss,
            )  # fmt: skip
        right_up = np.array([f.right_up_mm for f in found]).reshape(-1, 2)
        centres.take_solved(views, right_up)
        moved = np.sqrt(np.mean(np.sum(right_up**2, axis=1))) if len(views) else 0.0
        self.stream.write(
            f"camera centres: solved against the field after step {self.it}: moved "
            f"{moved / centres.footprint:.3f} px (rms)\n"
        )

    # --- checkpoints --------------------------------------------------------------------------
    def save_checkpoint(self) -> None:
        self.out.save_checkpoint(
            Checkpoint(
                params=self.params,
                iteration=self.it,
                resolution=self.kind.resolution(self.field),
                best=self.best,
                adam=self.optimizer.state(),
                eta_max=self.eta_max,
                centres=self.objective.centres.state() if self.objective.centres else {},
            )
        )

    def load_checkpoint(self) -> None:
        ckpt = self.out.checkpoint()
        self.box, eta_max = self.out.box_and_top()
        self.eta_max = float(ckpt.eta_max or eta_max or self.eta_max)
        # bound (and its occupancy built) as at iteration 0: its rebuilds then fall where an
        # uninterrupted run's did
        self.bind(self.kind.run_field(self.cfg, self.box, self.eta_max, ckpt.resolution))
        if len(ckpt.params) != len(self.params):
            raise ClrefractError(
                f"{self.out.checkpoint_path}: checkpoint has {len(ckpt.params)} parameters, "
                f"the configured field has {len(self.params)}"
            )
        self.params[:] = ckpt.params
        self.field.set_data(self.params)
        self.bound.upload(self.it)
        self.it = ckpt.iteration
        self.best = ckpt.best
        self.optimizer = optimizer_for(self, ckpt)
        self.optimizer.restore(self, ckpt)
        if self.objective.centres is not None:
            self.objective.centres.restore(ckpt.centres)
