"""Issue 9: from a perturbed start, adjoint gradients and Adam on the hash grid + MLP lower
the loss of views they never trained on.

The scene is a small Luneburg lens (a graded-index sphere, eta from sqrt(2) at the centre
to 1 at the rim); the start is the hash grid fitted to the same lens shrunk to 0.8 of its
radius. Glass spheres are not tested here: on them no setting measured so far lowers the
held-out loss reliably (docs/design/distillation.md).
"""

import dataclasses
import io

import numpy as np
import pytest

from clrefract.fit import Fit, load_config
from clrefract.fit.optimizers import AdamSteps
from clrefract.fit.starts import distil_start
from clrefract.report import scene_truth
from clrefract.synth import MakeOptions, make_dataset


@pytest.fixture(scope="module")
def lens(tmp_path_factory):
    out = tmp_path_factory.mktemp("luneburg")
    make_dataset("luneburg", out, MakeOptions(views=16, res=32, env_width=256, volume_res=16))
    return out


def test_six_cheap_steps_of_hash_grid_descent_lower_the_held_out_loss(lens, tmp_path):
    """The benchmark below in a few seconds: half its rays and 1 mm steps along them (the
    lens bends rays gently everywhere), six steps of Adam from a shorter distillation take
    the held-out loss under 0.95 of the start's (measured 0.90; 0.92 after two steps)."""
    cfg = load_config(
        None,
        dict(field="hashgrid", init="empty", eta_max=1.5, levels=4, log2_table=12, hidden=16,
             optimizer="adam",
             distil_iterations=100, batch=1024, step=1.0, iterations=6, val_views=4,
             lr_table=1e-2, lr_mlp=1e-3, validate_every=0, checkpoint_every=0),
    )  # fmt: skip
    fit = Fit(lens, tmp_path / "run", cfg, stream=io.StringIO())
    truth = scene_truth(fit.ds)
    distil_start(fit, dataclasses.replace(truth, radius=0.8 * truth.radius))
    fit.optimizer = AdamSteps(fit)
    start = fit.validation_loss()
    held_out = []
    for _ in range(cfg.iterations):
        fit.step()
        held_out.append(fit.validation_loss())
    assert np.all(np.isfinite(held_out))
    assert held_out[-1] < 0.95 * start, (start, held_out)


@pytest.mark.benchmark  # about 160 s; test_six_cheap_steps_of_hash_grid_descent_lower_the_...
def test_hash_grid_descent_lowers_the_held_out_loss_of_a_perturbed_lens(lens, tmp_path):
    cfg = load_config(
        None,
        dict(field="hashgrid", init="empty", eta_max=1.5, levels=4, log2_table=12, hidden=16,
             optimizer="adam",
             distil_iterations=150, batch=2048, iterations=10, val_views=4,
             lr_table=1e-2, lr_mlp=1e-3, validate_every=0, checkpoint_every=0),
    )  # fmt: skip
    fit = Fit(lens, tmp_path / "run", cfg, stream=io.StringIO())
    truth = scene_truth(fit.ds)
    distil_start(fit, dataclasses.replace(truth, radius=0.8 * truth.radius))
    fit.optimizer = AdamSteps(fit)
    start = fit.validation_loss()
    held_out = []
    for _ in range(cfg.iterations):
        fit.step()
        held_out.append(fit.validation_loss())
    # measured: 0.80 after 5 steps, 0.74 after 15 (rates 10x the glass defaults; at the
    # defaults, 0.994: a hull start of glass needs the small steps, see FitConfig.lr_table)
    assert held_out[-1] < 0.85 * start, (start, held_out)
    assert np.all(np.isfinite(held_out))
