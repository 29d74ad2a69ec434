"""A field bound to its gradient engine and parameters: what an optimiser moves. A fit holds
one; a hash grid's line search holds a second, the level set it follows."""

from __future__ import annotations

import numpy as np

from ..tracer import TraceSettings
from .config import FitConfig
from .kinds import kind_of, step_mm


def forward_settings(cfg: FitConfig, interface_steps: bool = True) -> TraceSettings:
    """How a run's field is traced forward (rendered, scored, validated): its step,
    precision and lanes, flying straight through the cells where eta is constant."""
    return TraceSettings(
        step=step_mm(cfg),
        precision=cfg.precision,
        lanes=cfg.lanes or None,
        interface_steps=interface_steps,
        skip_empty=True,
    )


def train_settings(cfg: FitConfig, field, step: float = 0.0) -> TraceSettings:
    """How a fit traces `field` forward and back while it trains it: rays skip empty space
    only through the kind of field its adapter names."""
    return TraceSettings(
        step=step or step_mm(cfg),
        precision=cfg.precision,
        lanes=cfg.lanes or None,
        queues=cfg.queues,
        checkpoint_every=cfg.backward_checkpoints,
        growth_max=cfg.adjoint_growth_max,
        adjoint=cfg.adjoint,
        skip_empty=cfg.skip_empty and field.kind == kind_of(cfg).skipping_kind(cfg),
        occupancy_res=cfg.occupancy_res,
    )


def engine_for(field, box, cfg: FitConfig, runtime, step: float = 0.0):
    """The gradient engine that trains `field`, split over MPI ranks, if any."""
    from ..parallel import shard
    from ..tracing import engine_for as field_engine

    settings = train_settings(cfg, field, step)
    engine = field_engine(field, box, settings, runtime=runtime, loss_space=cfg.loss)
    return shard(engine, cfg.chunks)


class Bound:
    """A field, its parameters (float64, the optimiser's copy) and the engine that traces
    it; with skip_empty, the occupancy kept ahead of its parameters."""

    def __init__(self, field, engine, occupancy=None, free: np.ndarray | None = None):
        self.field, self.engine = field, engine
        self.params = np.array(field.data(), np.float64)
        self.occupancy = occupancy
        self.free = free  # the parameters a start lets move (None: all)

    @property
    def tracer(self):
        return self.engine.tracer

    def upload(self, it: int, stepped: bool = False) -> None:
        """Send the parameters to the device; with skip_empty, rebuild the occupancy: always
        after a jump of the parameters (a start, a resume), when due after a training step."""
        tracer = self.engine.tracer
        tracer.upload_field()
        if self.occupancy is not None and tracer.skip_empty:
            self.occupancy.update(it, self.field, tracer, self.free, force=not stepped)

    def set_params(self, params: np.ndarray, it: int) -> None:
        """New parameters, on the device, with the occupancy rebuilt from them: a resumed run
        then skips the same cells (in float32 a flight rounds otherwise than the steps it
        replaces)."""
        self.params[:] = params
        self.field.set_data(self.params)
        self.upload(it)

    def with_top(self, cfg: FitConfig, eta_max: float, it: int) -> None:
        """The field's upper bound moved (a hash grid's follows its guide's index), sent to
        the device with the parameters."""
        kind_of(cfg).with_top(self.field, eta_max)
        self.upload(it)
