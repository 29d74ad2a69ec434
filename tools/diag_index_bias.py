"""How a shape's error moves the index the photometric loss picks: the true object of a
family dataset on the start's level-set grid, its distance perturbed by a smooth random
field of a given RMS (mm), and for each perturbation the index of lowest loss on the fit's
fixed batch of mask rays (the start search's batch).

    python tools/diag_index_bias.py DATA [--res 64] [--batch 8192] [--errors 0 0.25 0.5 1]
                                         [--seeds 3] [--sigma 1.5] [--losses fit l1 ncc]
                                         [--json OUT]

The perturbation is white noise smoothed by a Gaussian of `sigma` cells, scaled to the RMS;
indices are scanned from the truth - 0.3 to the truth + 0.1 in steps of 0.025. The grid and
batch default to a level-set fit's. --losses picks by other losses of the same renders too:
"fit" is the fit's own; "l1" the mean absolute sRGB difference; "ncc" minus the correlation
of render and photograph per channel (blind to how strongly the renders vary, so not drawn
to the duller images a lower index gives).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

from clrefract.fields.levelset import LevelSetField
from clrefract.fit import Fit, FitConfig
from clrefract.fit_linesearch import set_params
from clrefract.fit_start import START_BATCH
from clrefract.loss import srgb
from clrefract.report import scene_truth


def _ncc(loss, renders, photos) -> float:
    r, t = renders - renders.mean(0), photos - photos.mean(0)
    return -float(np.mean((r * t).sum(0) / np.sqrt((r * r).sum(0) * (t * t).sum(0) + 1e-30)))


LOSSES = {
    "fit": lambda loss, renders, photos: loss,
    "l1": lambda loss, renders, photos: float(np.mean(np.abs(renders - photos))),
    "ncc": _ncc,
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, help="a dataset with a ground truth (`dataset make`)")
    fit_cfg = FitConfig(field="levelset")
    ap.add_argument("--res", type=int, default=fit_cfg.res, help="level-set nodes a side")
    ap.add_argument("--batch", type=int, default=fit_cfg.batch, help="mask rays of the loss")
    ap.add_argument("--errors", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0])
    ap.add_argument("--seeds", type=int, default=3, help="perturbations per RMS above 0")
    ap.add_argument("--sigma", type=float, default=1.5, help="smoothing of the error, cells")
    ap.add_argument("--losses", nargs="+", default=["fit"], choices=sorted(LOSSES))
    ap.add_argument("--json", type=Path, default=Path("bench_results/index_bias.json"))
    args = ap.parse_args()

    cfg = FitConfig(field="levelset", res=args.res, batch=args.batch)
    with tempfile.TemporaryDirectory() as tmp:
        fit = Fit(args.data, Path(tmp), cfg, stream=sys.stderr)
        truth = scene_truth(fit.ds)
        if truth is None:
            print(f"{args.data}: no ground truth to perturb", file=sys.stderr)
            return 2
        fit._bind(fit._make_field(fit.start_grid()))  # the start's field, without its search
        shape = fit.field.phi.shape
        exact = LevelSetField.from_sdf(
            lambda p: truth.sdf(p)[0], fit.box, shape, truth.eta, cfg.width
        ).data()[:-1]
        idx = fit._mask_batch(START_BATCH)
        etas = np.round(np.arange(truth.eta - 0.3, truth.eta + 0.1 + 1e-9, 0.025), 4)

        photos = srgb(fit.rgb[idx])[0]

        def pick(phi: np.ndarray) -> dict:
            """Per loss, the scanned index of lowest loss with distance phi."""
            scores = {name: [] for name in args.losses}
            for e in etas:
                set_params(fit, np.append(phi, e))
                loss, radiance = fit.forward_render(idx)
                renders = srgb(radiance)[0]
                for name in args.losses:
                    scores[name].append(LOSSES[name](loss, renders, photos))
            return {name: float(etas[int(np.argmin(v))]) for name, v in scores.items()}

        cell = float(np.max(fit.box.size) / (max(shape) - 1))
        print(
            f"{args.data}: index {truth.eta}, {shape[0]}^3 nodes of {cell:.2f} mm, "
            f"step {fit.cfg.step_mm:.3g} mm, {len(idx)} rays"
        )
        print(f"{'error rms mm':>12} {'loss':>5}  index picked per perturbation")
        rows = []
        for rms in args.errors:
            picks = []
            for seed in range(args.seeds if rms > 0 else 1):
                noise = gaussian_filter(np.random.default_rng(seed).normal(size=shape), args.sigma)
                noise *= rms / noise.std()
                picks.append(pick(exact + noise.ravel()))
            for name in args.losses:
                got = [p[name] for p in picks]
                rows.append(
                    {"error_rms_mm": rms, "loss": name, "picks": got, "mean": float(np.mean(got))}
                )
                print(f"{rms:12.3g} {name:>5}  " + " ".join(f"{p:.3f}" for p in got), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(
        json.dumps(
            {"data": str(args.data), "truth": truth.eta, "cell_mm": cell, "rows": rows}, indent=1
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
