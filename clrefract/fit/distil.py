"""Distillation: a hash grid fitted to another field (a level set, a scene's truth) at points
of its box, on the fit's device or on the host."""

from __future__ import annotations

import numpy as np

from ..errors import ClrefractError
from ..log import Progress

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
