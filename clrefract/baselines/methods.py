"""The four methods of the paper's Table 1 by name, and clrefract's interface model and its
command line's default as rows beside them, each run the same way on a dataset.

- grid: the paper's "Grid-based refraction": clrefract's voxel fit (same curved-ray tracer,
  same adjoint, same start from the visual hull) on a uniform 128^3 grid with trilinear
  weights; only the representation differs from clrefract's own settings;
- meridian, synapse: the straight-ray baselines (clrefract.baselines.straight): a neural
  field of density and colour (hash encoding + MLP) and a 128^3 voxel grid;
- vertexnet: the paper's own method, clrefract's hash grid + MLP fit through curved rays;
- interface: not the paper's: a zero-width surface (phi on a B-spline grid) with one index
  inside, rays refracted by Snell's law at each crossing (fields/interface.py), fitted at its
  kind's defaults (the descent from the visual hull). It has no figures in the paper.
- auto: what `clrefract fit` runs without --field-kind: the interface, the polytope (flat
  faces) and a voxel grid started, the one the held-out views prefer trained on.

`settings` (a protocol's, for this method) override the method's defaults; keys that are not
FitConfig (curved) or StraightConfig (straight) fields are ignored.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields
from pathlib import Path

from ..errors import ClrefractError


@dataclass(frozen=True)
class Method:
    name: str
    paper_name: str
    rays: str  # "curved" or "straight"
    fit: dict  # FitConfig (curved) or StraightConfig (straight) settings
    # PSNR, SSIM, D_C (mm) of SPEC section 5's Table 1; None: a row the paper does not have
    paper: tuple[float, float, float] | None


METHODS = {
    m.name: m
    for m in (
        Method(
            "grid",
            "Grid-based refraction",
            "curved",
            # the paper's baseline as it describes it: Adam from the hull, whatever the
            # voxel kind's own defaults become
            dict(
                field="voxel",
                interp="trilinear",
                res=128,
                res_schedule=(),
                optimizer="adam",
                init="hull",
                lr=5e-3,
                mask_share=0.0,
            ),
            (22.45, 0.812, 4.12),
        ),
        Method(
            "meridian",
            "Meridian Renderer",
            "straight",
            dict(style="meridian"),
            (24.12, 0.854, 3.05),
        ),
        Method(
            "synapse", "Synapse-Volumetric", "straight", dict(style="synapse"), (26.89, 0.891, 1.88)
        ),
        Method("vertexnet", "Vertex-Net", "curved", dict(field="hashgrid"), (31.54, 0.942, 0.74)),
        Method("interface", "Interface (SDF + Snell)", "curved", dict(field="interface"), None),
        Method("auto", "clrefract fit's default", "curved", dict(field="auto"), None),
    )
}


def _known(cls, settings: dict) -> dict:
    names = {f.name for f in fields(cls)}
    return {k: v for k, v in settings.items() if k in names}


def run_method(
    name: str, dataset: Path, out: Path, settings: dict | None = None, stream=None
) -> dict:
    """Train method `name` on dataset into run folder `out`; returns its wall time in seconds
    (dataset loading, start and training; scoring is `clrefract eval`'s)."""
    if name not in METHODS:
        raise ClrefractError(f"unknown method {name!r}; methods are {', '.join(METHODS)}")
    m = METHODS[name]
    t0 = time.perf_counter()
    if m.rays == "straight":
        from .straight import StraightConfig, fit_straight

        cfg = StraightConfig(**_known(StraightConfig, {**m.fit, **(settings or {})}))
        fit_straight(dataset, out, cfg, stream=stream)
    else:
        from ..fit import FitConfig, load_config, run_fit

        cfg = load_config(None, _known(FitConfig, {**m.fit, **(settings or {})}))
        cfg.test_views = 0  # the table scores every test view through `eval` instead
        run_fit(dataset, out, cfg, stream=stream)
    return {"method": name, "wall_seconds": time.perf_counter() - t0}
