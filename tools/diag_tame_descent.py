"""Can gradient descent improve a level-set start? Full-batch descent on a fixed set of
training rays, with the rays whose adjoint grows past a bound left out of the loss and the
shape gradient smoothed on the grid.

    python tools/diag_tame_descent.py RUN [--rays 60000] [--iterations 8] [--growth 10]
        [--sigma 3] [--steps 0.003,0.01,0.03,0.1] [--save PATH]
        [--json bench_results/diag_tame_descent.json]

RUN is a level-set run folder (`clrefract fit --field levelset`, or a `bench_reconstruction.py`
run); its field.npz is the start and its config the tracer's. Each iteration takes the loss
and adjoint gradient of RAYS rays through the masks of the training views (held-out views
excluded), keeps those that exit with an adjoint growth of at most GROWTH (0: every
exiting one), and takes one step of `--optimizer line-search` on them
(clrefract/fit_linesearch.py: the gradient smoothed by SIGMA grid cells, 0: none; phi moved
by the best of STEPS, the largest node move in mm, or not at all). It prints the loss of all
the rays and of the kept ones, the test views' PSNR and SSIM, the chamfer distance and the
held-out loss.

Why: rays that graze or reflect inside glass change their exit by degrees for a 10 nm move
of the surface, so the loss of all rays is rough at every step a line search can try, while
the loss of the others follows its gradient; and the raw gradient's steepest directions fit
pixels through node-scale ripples, which the smoothing removes.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import time
from pathlib import Path

import numpy as np


def main() -> None:
    from clrefract.fit import Fit, load_config
    from clrefract.fit_linesearch import search_along, set_params, tame_rays
    from clrefract.report import score_field

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--rays", type=int, default=60000)
    ap.add_argument("--iterations", type=int, default=8)
    ap.add_argument("--growth", type=float, default=10.0, help="0: keep every exiting ray")
    ap.add_argument("--sigma", type=float, default=3.0, help="grid cells; 0: raw gradient")
    ap.add_argument("--steps", default="0.003,0.01,0.03,0.1", help="largest node moves, mm")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save", type=Path, help="write the final level set here (.npz)")
    ap.add_argument("--json", default="bench_results/diag_tame_descent.json")
    args = ap.parse_args()

    cfg = load_config(args.run / "config.toml", {})
    if cfg.field != "levelset":
        raise SystemExit(f"{args.run}: a level-set run is needed, this one fits {cfg.field}")
    cfg.keep_growth = args.growth if args.growth > 0 else math.inf
    cfg.grad_sigma = args.sigma
    cfg.line_steps = tuple(float(s) for s in args.steps.split(",") if s)
    dataset = Path(json.loads((args.run / "run.json").read_text())["dataset"])
    fit = Fit(dataset, args.run, cfg, stream=io.StringIO())
    fit.load_checkpoint()  # binds a level set on the run's box
    with np.load(args.run / "field.npz") as z:
        set_params(fit, np.concatenate([z["phi"].ravel(), [float(z["eta"])]]))
    rng = np.random.default_rng(args.seed)
    marked = fit._marked_pool()
    rays = rng.choice(marked, min(args.rays, len(marked)), replace=False)

    def scores() -> dict:
        s = score_field(fit)
        return {
            "test_psnr": s["test_psnr"],
            "test_ssim": s["test_ssim"],
            "chamfer_mm": s.get("chamfer_mm"),
            "val_loss": fit.validation_loss(),
        }

    rows = [{"iteration": 0, **scores()}]
    cols = ("iteration", "loss_all", "kept", "loss_kept", "loss_kept_after", "step_mm",
            "test_psnr", "test_ssim", "chamfer_mm", "val_loss", "seconds")  # fmt: skip
    print("  ".join(f"{c:>10}" for c in cols))

    def show(row: dict) -> None:
        cells = []
        for c in cols:
            v = row.get(c, "")
            cells.append(f"{v:>10.5g}" if isinstance(v, float) else f"{v!s:>10}")
        print("  ".join(cells), flush=True)

    show(rows[0])
    for it in range(1, args.iterations + 1):
        t0 = time.perf_counter()
        first, ok = tame_rays(fit, rays)
        row = {"iteration": it, "loss_all": float(first.loss), "kept": int(ok.sum())}
        if ok.any():
            row.update(search_along(fit, rays[ok]))
        row.update(scores(), seconds=time.perf_counter() - t0)
        rows.append(row)
        show(row)
    if args.save:
        fit.field.save(args.save)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    report = {"args": {k: str(v) for k, v in vars(args).items()}, "rays": len(rays), "rows": rows}
    out.write_text(json.dumps(report, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
