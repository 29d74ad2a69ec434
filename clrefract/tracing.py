"""The tracer and the gradient engine of a field, as the field says it is traced
(`Field.traced_by`): the caller never asks what kind of field it holds."""

from __future__ import annotations

from .fields.base import Box
from .gradient import GradientEngine
from .interface import InterfaceEngine, InterfaceTracer
from .tracer import Tracer, TraceSettings

TRACERS = {"eikonal": Tracer, "interface": InterfaceTracer}
ENGINES = {"eikonal": GradientEngine, "interface": InterfaceEngine}


def tracer_for(field, box: Box, settings: TraceSettings, *, runtime=None, occupancy=None):
    """The forward tracer of `field` in `box`."""
    cls = TRACERS[field.traced_by]
    return cls(field, box, settings, runtime=runtime, occupancy=occupancy)


def engine_for(field, box: Box, settings: TraceSettings, *, runtime=None, loss_space="srgb"):
    """The loss-and-gradient engine of `field` in `box`."""
    cls = ENGINES[field.traced_by]
    return cls(field, box, settings, runtime=runtime, loss_space=loss_space)
