"""`load_config`: defaults, then a TOML file, then the command line's flags, with the field
kind's and the optimiser's own defaults and checks."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ClrefractError
from .config import FitConfig, check_choices, coerced, read_toml
from .kinds import kind_named


def load_config(path: Path | None, overrides: dict) -> FitConfig:
    """Defaults, then the TOML file, then command-line overrides (None values ignored)."""
    items: dict = read_toml(path) if path is not None else {}
    items.update({k: v for k, v in overrides.items() if v is not None})
    kind = kind_named(items.get("field", FitConfig.field))
    given = frozenset(items) - {"field"}
    kind.defaults(items)
    cfg = coerced(items)
    if kind.candidates:
        # what the file and flags said, for each candidate's own defaults to fill the rest
        # (a value equal to FitConfig's default is no less given)
        cfg.given = given
    normalise(cfg)
    cfg.validate()
    kind.validate(cfg)
    if cfg.optimizer == "line-search":
        check_line_search(cfg)
    check_choices(cfg)
    return cfg


def normalise(cfg: FitConfig) -> None:
    """The list-valued keys as tuples of floats (one number is a list of one)."""
    cfg.grad_sigma = _floats(cfg.grad_sigma, "grad_sigma", lambda s: s >= 0, _SIGMA_HINT)
    cfg.line_steps = _floats(cfg.line_steps, "line_steps", lambda s: s > 0, _STEPS_HINT)
    cfg.index_steps = _floats(cfg.index_steps, "index_steps", lambda s: s > 0, _INDEX_HINT, ())


_SIGMA_HINT = "must be one or more scales >= 0 in cells (0: no smoothing)"
_STEPS_HINT = "must be positive moves in mm"
_INDEX_HINT = "must be positive index moves (or empty)"


def _floats(value, name: str, ok, hint: str, empty=None) -> tuple:
    values = value if isinstance(value, list | tuple) else (value,)
    try:
        values = tuple(float(s) for s in values)
    except (TypeError, ValueError):
        values = None
    if values is None or (not values and empty is None):
        raise ClrefractError(f"{name} {hint}, got {value}")
    if not all(ok(s) and np.isfinite(s) for s in values):
        raise ClrefractError(f"{name} {hint}, got {value}")
    return values


def check_line_search(cfg: FitConfig) -> None:
    """What the line search needs of a fit's config (its field kind's check aside)."""
    if cfg.line_batch < 0:
        raise ClrefractError(f"line_batch must be >= 0 (0: batch), got {cfg.line_batch}")
    if cfg.refit_iterations < 1:
        raise ClrefractError(f"refit_iterations must be at least 1, got {cfg.refit_iterations}")
    if cfg.refit not in ("best", "step"):
        raise ClrefractError(f"refit must be 'best' or 'step', got {cfg.refit!r}")
    if not (cfg.keep_growth > 1 and np.isfinite(cfg.keep_growth)):
        raise ClrefractError(f"keep_growth must be above 1, got {cfg.keep_growth}")
    if cfg.env_blur > 0 or cfg.block > 1:
        raise ClrefractError(
            "optimizer 'line-search' compares sharp pixels: set env_blur = 0 and block = 0"
        )
