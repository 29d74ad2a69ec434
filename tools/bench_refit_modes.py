"""A hash grid's line-search step two ways, side by side from one run's state: with the grid
fitted to its level set after every move and the grid validated (refit = "step"), and with
the level set validated and the grid fitted once at the end (refit = "best", the default).
Each way resumes a copy of RUN, takes --steps steps, and times each step and its
validation; the ways alternate --rounds times, so that the machine's drift falls on both.
At the end, the "best" way's grid is fitted to its best step (FINAL_REFIT) and timed.

    python tools/bench_refit_modes.py RUN DATASET [--steps 2] [--rounds 2]
        [--json bench_results/refit_modes.json]

RUN is a hash-grid run folder from the hull (e.g. one of tools/bench_reconstruction.py's).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from bench_line_search import resumed_copy

from clrefract.fit.runfolder import Best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("run", type=Path)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--json", default="bench_results/refit_modes.json")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for mode in ("step", "best"):
                fit = resumed_copy(args.run, args.dataset, Path(tmp) / mode, {"refit": mode})
                fit.cfg.iterations = fit.it + args.steps
                for _ in range(args.steps):
                    t0 = time.perf_counter()
                    step = fit.step()
                    t1 = time.perf_counter()
                    val = fit.validation_loss()
                    rows.append(
                        dict(
                            round=r,
                            refit=mode,
                            step_s=t1 - t0,
                            validation_s=time.perf_counter() - t1,
                            val_loss=val,
                            move_mm=step["step_mm"],
                        )
                    )
                if mode == "best" and r == args.rounds - 1:
                    guided = fit.optimizer
                    fit.best = Best(0.0, fit.it, guided.guide.params.copy())  # its last step
                    final = guided.refit_to_best(fit)
    print(
        f"{'refit':6s} {'round':>5s} {'step s':>7s} {'valid. s':>8s} {'held-out':>9s} {'move':>6s}"
    )
    for row in rows:
        print(
            f"{row['refit']:6s} {row['round']:5d} {row['step_s']:7.1f} "
            f"{row['validation_s']:8.1f} {row['val_loss']:9.6f} {row['move_mm']:6.3f}"
        )
    for mode in ("step", "best"):
        per = [r["step_s"] + r["validation_s"] for r in rows if r["refit"] == mode]
        print(f"{mode}: {sum(per) / len(per):.1f} s a validated step (mean of {len(per)})")
    print(
        f"best: the grid fitted to its last step in {final['seconds']:.1f} s "
        f"(eta RMS {final['distilled_rms']:.5f})"
    )
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rows": rows, "final_refit": final}, indent=2))


if __name__ == "__main__":
    main()
