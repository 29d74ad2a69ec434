"""Shared pieces of the gradient tests: a smooth environment and directional central
differences of the discretised forward renderer."""

import numpy as np

from clrefract.envmap import EnvMap, pixel_directions
from clrefract.loss import photometric_loss


def smooth_env():
    """A smooth analytic environment at high resolution: the loss is smooth enough for
    finite differences (bilinear texel kinks are far below the FD perturbation)."""
    d = pixel_directions(2048, 1024)
    img = np.stack(
        [
            1 + 0.5 * np.sin(3 * d[..., 0] + 1) * np.cos(2 * d[..., 2]),
            1 + 0.5 * np.cos(4 * d[..., 1]),
            1 + 0.3 * d[..., 2],
        ],
        -1,
    )
    return EnvMap(img * 0.4)


def directional_errors(eng, o, d, env, target, grad, p0, directions, eps):
    """Relative error of <grad, u> against (J(p0 + eps u) - J(p0 - eps u)) / 2 eps for each
    direction u, J being the forward renderer's loss; leaves the engine at p0."""

    def loss(p):
        eng.set_params(p)
        tr = eng.tracer.trace(o, d)
        ok = (tr.status == 0).astype(float)
        return photometric_loss(env, tr.last_velocity, target, weight=ok)[0]

    errs = []
    for u in directions:
        fd = (loss(p0 + eps * u) - loss(p0 - eps * u)) / (2 * eps)
        errs.append(abs(fd - grad @ u) / abs(fd))
    eng.set_params(p0)
    return np.array(errs)
