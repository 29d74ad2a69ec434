"""Fingerprint the fit on a tiny protocol, to show a refactor leaves it unchanged.

    python tools/fit_fingerprint.py OUT            three tiny float64 fits into OUT (JSON)
    python tools/fit_fingerprint.py --compare A B  their metrics and results side by side

The three fits (a 15-view 24 x 24 sphere): a voxel grid with Adam, a level set with the line
search, and a hash grid following its level set. Run it once with the old checkout first on
PYTHONPATH (a git worktree), once with the new. Timings are left out; the backward pass adds
with float atomics, so float64 runs differ by about 1e-10 between two runs of one checkout:
the comparison prints the largest relative difference of each fit and any non-numeric one.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

CASES = {
    "voxel_adam": dict(field="voxel", res=16, iterations=6, batch=2048, validate_every=2),
    "levelset_ls": dict(field="levelset", optimizer="line-search", res=24, iterations=3),
    "hashgrid_guided": dict(
        field="hashgrid", res=24, iterations=3, line_batch=2048, distil_iterations=60,
        refit_iterations=10, levels=4, log2_table=10, n_max=32, hidden=16,
    ),
}  # fmt: skip
COMMON = dict(batch=2048, val_views=3, precision="float64")
TIMING = ("seconds", "rays_per_s", "train_seconds")


def run(out: Path) -> None:
    from clrefract.fit import load_config, prepare_fit
    from clrefract.synth import MakeOptions, make_dataset

    out.mkdir(parents=True, exist_ok=True)
    data = out / "sphere24"
    if not data.exists():
        make_dataset("sphere", data, MakeOptions(views=15, res=24, env_width=256, volume_res=16))
    for name, settings in CASES.items():
        folder = out / name
        shutil.rmtree(folder, ignore_errors=True)
        result = prepare_fit(data, folder, load_config(None, {**COMMON, **settings})).run()
        rows = [json.loads(x) for x in (folder / "metrics.jsonl").read_text().splitlines()]
        (out / f"{name}.json").write_text(json.dumps({"metrics": rows, "results": result}))


def differences(a, b, path="") -> tuple[float, list[str]]:
    """The largest relative difference of the numbers, and what differs otherwise."""
    if isinstance(a, dict) and isinstance(b, dict):
        worst, other = 0.0, []
        for k in sorted(set(a) | set(b)):
            if k in TIMING:
                continue
            if k not in a or k not in b:
                other.append(f"{path}/{k}: in one only")
                continue
            w, o = differences(a[k], b[k], f"{path}/{k}")
            worst, other = max(worst, w), other + o
        return worst, other
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return 0.0, [f"{path}: {len(a)} against {len(b)} items"]
        pairs = [differences(x, y, f"{path}[{i}]") for i, (x, y) in enumerate(zip(a, b))]
        return max((w for w, _ in pairs), default=0.0), [o for _, os in pairs for o in os]
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool):
        if a == b or (math.isnan(a) and math.isnan(b)):
            return 0.0, []
        return abs(a - b) / max(abs(a), abs(b)), []
    return 0.0, [] if a == b else [f"{path}: {a!r} against {b!r}"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, nargs="?")
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"))
    args = ap.parse_args()
    if not args.compare:
        if args.out is None:
            ap.error("give OUT, or --compare A B")
        run(args.out)
        return 0
    print(f"{'fit':16s} {'metrics rel.':>13s} {'results rel.':>13s}  other")
    for name in CASES:
        a, b = (json.loads((d / f"{name}.json").read_text()) for d in args.compare)
        wm, om = differences(a["metrics"], b["metrics"])
        wr, orr = differences(a["results"], b["results"])
        print(f"{name:16s} {wm:13.2e} {wr:13.2e}  {'; '.join(om + orr) or '-'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
