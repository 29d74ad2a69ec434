"""`clrefract fit`: recover eta(x) from a dataset with the adjoint gradient.

The parts, in the order their imports flow:
    config       FitConfig and its TOML
    kinds        one adapter per field kind (voxel, levelset, hashgrid, interface, polytope)
    configure    load_config: defaults, file, flags; the kind's and optimiser's checks
    runfolder    the run folder's files, written atomically
    rays         training rays, the held-out split, batches (with their tags), blur
    objective    the loss, its gradient, the held-out loss
    binding      a field bound to its engine and parameters
    distil       a hash grid fitted to another field
    starts       empty, the hull (voxel, level set, polytope), distilled (hash grid)
    linesearch   a level set's line-search step
    finishes     the size and index search, a narrowed run's judgement
    optimizers   Adam, the line search, the guided line search
    trainer      Fit: one run's state
    loop         train(): the loop and the finish
    session      prepare_fit, extend_run, field_from_run
    mpi          run_fit, in one process or over MPI ranks
"""

from .binding import forward_settings
from .config import FitConfig, to_toml
from .configure import load_config
from .distil import fit_to_field
from .finishes import narrow_run
from .kinds import (
    HASHGRID_LINE_SEARCH_ITERATIONS,
    LINE_SEARCH_ITERATIONS,
    LINE_SEARCH_PATIENCE,
    guide_config,
    hashgrid_config,
    interface_step_scale,
    kind_of,
    make_field,
    step_mm,
    voxel_step,
)
from .loop import FitDiverged, train
from .mpi import run_fit
from .rays import Tag
from .runfolder import RunFolder
from .session import extend_run, field_from_run, prepare_fit
from .trainer import Fit

__all__ = [
    "HASHGRID_LINE_SEARCH_ITERATIONS",
    "LINE_SEARCH_ITERATIONS",
    "LINE_SEARCH_PATIENCE",
    "Fit",
    "FitConfig",
    "FitDiverged",
    "RunFolder",
    "Tag",
    "extend_run",
    "field_from_run",
    "fit_to_field",
    "forward_settings",
    "guide_config",
    "hashgrid_config",
    "interface_step_scale",
    "kind_of",
    "load_config",
    "make_field",
    "narrow_run",
    "prepare_fit",
    "run_fit",
    "step_mm",
    "to_toml",
    "train",
    "voxel_step",
]
