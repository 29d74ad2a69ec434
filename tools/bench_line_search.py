"""Line-search settings side by side from one start: each variant resumes a copy of the same
start (a hash grid's or a level set's, its checkpoint of iteration 0) with its own settings,
takes the steps, and is scored on the test views as a fit ends. Comparing whole fits instead
would compare their starts too: near-equal candidates of the start's search trade places
between runs (the backward pass's float atomics).

    python tools/bench_line_search.py DATASET [--start RUN] [--iterations 32]
        [--variants "sigma3:grad_sigma=3" "scales:grad_sigma=[3,6,12]"]
        [--out bench_results/line_search] [--json bench_results/line_search.json]

Without --start, a hash grid's start from the hull is made first (OUT/start, with the fit's
defaults). A variant is NAME:KEY=VALUE;KEY=VALUE with FitConfig keys and TOML values, as
in a config file. Prints, per variant: the held-out loss at each quarter of the steps and
its best, the test PSNR / SSIM / chamfer of the start and of the fit, the gain, and the
time per step.
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from clrefract.errors import ClrefractError
from clrefract.fit import load_config, prepare_fit, to_toml

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib


def parse_variant(text: str) -> tuple[str, dict]:
    """'name:key=value;key=value' -> (name, {key: value}), the values read as TOML."""
    name, _, body = text.partition(":")
    try:
        return name, tomllib.loads(body.replace(";", "\n"))
    except tomllib.TOMLDecodeError as exc:
        raise ClrefractError(f"variant {text!r}: {exc}") from None


def resumed_copy(run: Path, dataset: Path, copy: Path, settings: dict):
    """A fresh copy of the run folder `run`, resumed with `settings` over its config."""
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(run, copy)
    cfg = load_config(copy / "config.toml", settings)
    (copy / "config.toml").write_text(to_toml(cfg))
    return prepare_fit(dataset, copy, None, resume=True, stream=io.StringIO())


def make_start(dataset: Path, out: Path, iterations: int) -> Path:
    """A hash grid's start from the hull with the fit's defaults, unless OUT holds one."""
    if not (out / "checkpoint.npz").is_file():
        cfg = load_config(None, dict(field="hashgrid", iterations=iterations))
        prepare_fit(dataset, out, cfg, stream=sys.stderr)
    return out


def run_variant(start: Path, dataset: Path, out: Path, iterations: int, settings: dict) -> dict:
    fit = resumed_copy(start, dataset, out, {**settings, "iterations": iterations})
    if fit.it != 0:
        raise ClrefractError(f"{start}: its checkpoint is at step {fit.it}, not at its start")
    t0 = time.perf_counter()
    result = fit.run()
    seconds = time.perf_counter() - t0
    rows = [json.loads(line) for line in (out / "metrics.jsonl").open()]
    val = [r["val_loss"] for r in rows if "val_loss" in r]
    step_s = [r["seconds"] for r in rows if "seconds" in r]
    start_scores = json.loads((out / "start.json").read_text())
    return {
        "settings": settings,
        "val_loss": val,
        "best_val_loss": result.get("best_val_loss"),
        "best_iteration": result.get("best_iteration"),
        "start": {k: start_scores.get(k) for k in ("test_psnr", "test_ssim", "chamfer_mm")},
        "fit": {k: result.get(k) for k in ("test_psnr", "test_ssim", "chamfer_mm")},
        "gain_db": result.get("psnr_gain_over_start"),
        "step_seconds": float(np.median(step_s)) if step_s else None,
        "seconds": seconds,
    }


def table(rows: dict) -> str:
    lines = [
        "| variant | held-out loss at each quarter of the steps | best (step) | "
        "start PSNR / SSIM / "
        "chamfer | fit PSNR / SSIM / chamfer | gain | s per step |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        v = r["val_loss"]
        marks = " / ".join(f"{v[max(1, len(v) * q // 4) - 1]:.5f}" for q in (1, 2, 3, 4) if v)
        s, f = r["start"], r["fit"]
        lines.append(
            f"| {name} | {marks} | {r['best_val_loss']:.5f} ({r['best_iteration']}) | "
            f"{s['test_psnr']:.2f} / {s['test_ssim']:.3f} / {s['chamfer_mm']:.2f} | "
            f"{f['test_psnr']:.2f} / {f['test_ssim']:.3f} / {f['chamfer_mm']:.2f} | "
            f"{r['gain_db']:+.2f} | {r['step_seconds']:.1f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--start", type=Path, help="a run folder whose checkpoint is its start")
    ap.add_argument("--iterations", type=int, default=32)
    ap.add_argument(
        "--variants", nargs="+", default=["sigma3:grad_sigma=3", "scales:grad_sigma=[3,6,12]"]
    )
    ap.add_argument("--out", type=Path, default=Path("bench_results/line_search"))
    ap.add_argument("--json", default="bench_results/line_search.json")
    args = ap.parse_args()
    try:
        start = args.start or make_start(args.dataset, args.out / "start", args.iterations)
        rows = {}
        for text in args.variants:
            name, settings = parse_variant(text)
            print(f"{name}: {settings}", file=sys.stderr, flush=True)
            rows[name] = run_variant(
                start, args.dataset, args.out / name, args.iterations, settings
            )
    except ClrefractError as exc:
        sys.exit(f"bench_line_search: {exc}")
    print(table(rows))
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(
        json.dumps({"dataset": str(args.dataset), "start": str(start), "variants": rows}, indent=2)
    )


if __name__ == "__main__":
    main()
