"""Reconstruction benchmark: fit the sphere, the prism and the drop (or, with --suite family,
the glass solids of `dataset make`) on the quick protocol (100 views, 80 for training, 20 held
out) and score the test views, beside reference points measured with the same renderer and
metrics:

- empty: eta = 1 everywhere (what doing nothing scores);
- start: the fit's starting point (the visual hull filled by line search, no gradient step),
  scored from the run itself before its first step;
- fit: after the iterations, with the run's whole wall time (the start and the scoring of
  its test views included: what `clrefract fit` takes; the start's time column leaves its
  scoring out);
- ceiling: the ground truth on the same grid: its eta sampled at the nodes of a voxel grid,
  its signed distance at the nodes of a level set or an interface (not a bound there: a fit
  that places its own nodes can pass it), or a hash grid fitted to its eta and gradient the
  way a hash-grid start is fitted to its guide;
  --ceiling-grids scores it on finer grids too (is the grid's resolution the limit?).

For level sets and hash grids from the hull the index column gives the start's and the fit's
index beside the truth's.

    python tools/bench_reconstruction.py [--field levelset|voxel|hashgrid]
        [--suite paper|family] [--scenes sphere,prism,drop] [--res 128] [--grid 64]
        [--width MM] [--iterations N] [--config FIT.toml] [--ceiling-grids 128,192]
        [--json bench_results/reconstruction.json] [--shard i/n] [--merge] [--page PAGE.md]

--iterations defaults to the quick protocol's 100 Adam steps, or the fit's own count where
its optimiser is the line search (a hash grid's default: 32); --width and --config's keys
default to the fit's.

--shard i/n runs every n-th scene from the i-th and writes reconstruction.shard-i-of-n.json
(n jobs of a cluster array, or n processes on one machine); --merge then reads all n, prints
the whole table and writes --json. --page writes the table as a Markdown page (with the
command that measures it again), as docs/graded.md is written.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ADAM_ITERATIONS = 100  # the quick protocol's Adam steps


def dataset(scene: str, res: int, root: Path, views: int = 100) -> Path:
    """The scene's dataset ("blobs:2": the blob cluster of seed 2), made once."""
    from clrefract.synth import MakeOptions, make_dataset

    name, _, seed = scene.partition(":")
    out = root / (f"{name}{seed and '-' + seed}_{res}" + ("" if views == 100 else f"_{views}v"))
    if not (out / "scene.json").is_file():
        make_dataset(name, out, MakeOptions(views=views, res=res, seed=int(seed or 0)))
    return out


def ceiling_field(fit, truth, grid: int):
    """The truth in the fit's own representation, on a grid^3 grid where it has one (a hash
    grid: the truth distilled into it, as its start is); None where the truth has no surface
    for a surface model."""
    from clrefract.fields.voxel import VoxelGrid

    cfg = fit.cfg
    width = cfg.width  # the fit's own (--width's, where given)
    if cfg.field == "levelset":
        from clrefract.fields.levelset import LevelSetField

        ceiling = LevelSetField.from_sdf(lambda p: truth.sdf(p)[0], fit.box, grid, truth.eta, width)
    elif cfg.field == "interface":  # the truth's surface on the same grid, at zero width
        from clrefract.fields.interface import InterfaceField

        ceiling = (
            InterfaceField.from_sdf(lambda p: truth.sdf(p)[0], fit.box, grid, truth.eta, width)
            if hasattr(truth, "sdf")
            else None
        )
    elif cfg.field == "hashgrid":  # the truth fitted the way the start is
        from dataclasses import replace

        from clrefract.fit import fit_to_field, kind_of

        # the truth's index, not the start's; a graded medium's, the run's own top
        top = kind_of(cfg).eta_top(cfg, truth.eta) if hasattr(truth, "eta") else fit.eta_max
        hc = replace(fit.field.config, eta_max=top)
        ceiling = fit.field.__class__(hc, fit.box, seed=cfg.seed)
        fit_to_field(
            ceiling, truth, width, cfg.distil_iterations, cfg.seed, device=fit.distil_device()
        )
    else:
        ceiling = VoxelGrid.from_field(truth, fit.box, grid, interp=cfg.interp, eta_max=fit.eta_max)
    return ceiling


def bench_scene(scene: str, args) -> dict:
    import shutil

    from clrefract.fields.voxel import VoxelGrid
    from clrefract.fit import FitDiverged, load_config, prepare_fit
    from clrefract.report import scene_truth, score_field

    data = dataset(scene, args.res, Path(args.data), args.views)
    cfg = load_config(
        Path(args.config) if args.config else None,
        dict(
            field=args.field,
            width=args.width,
            res=args.grid,
            res_schedule=(),
            iterations=args.iterations,
            batch=args.batch,
            step=args.step,
            lr=args.lr,
        ),
    )
    if args.iterations is None and cfg.optimizer == "adam" and cfg.field != "voxel":
        cfg.iterations = ADAM_ITERATIONS
    from clrefract.runtime import default_runtime

    row: dict = {"scene": scene, "field": args.field, "res": args.res, "grid": args.grid}
    row["device"] = default_runtime().info.driver
    run = Path(args.runs) / scene.replace(":", "-")
    shutil.rmtree(run, ignore_errors=True)
    t0 = time.perf_counter()
    fit = prepare_fit(data, run, cfg)  # scores its start into start.json (auto: chooses)
    cfg = fit.cfg
    row["model"] = cfg.field
    prepared = time.perf_counter() - t0  # the start and its scoring, as `clrefract fit` runs
    row["start"] = json.loads((run / "start.json").read_text())
    row["empty"] = score_field(fit, VoxelGrid(np.ones((8, 8, 8)), fit.box))
    truth = scene_truth(fit.ds)
    ceiling = ceiling_field(fit, truth, args.grid)
    row["ceiling"] = score_field(fit, ceiling) if ceiling is not None else None
    row["ceilings"] = [  # the truth on finer grids: how far the grid's resolution holds it
        {"grid": g, **score_field(fit, c)}
        for g in args.ceiling_grids
        if cfg.field != "hashgrid" and (c := ceiling_field(fit, truth, g)) is not None
    ]
    t0 = time.perf_counter()
    try:
        res = fit.run()
    except FitDiverged as exc:  # its best field is scored all the same
        res = {**exc.result, "diverged": str(exc)}
    row["fit"] = {**res, "seconds": prepared + time.perf_counter() - t0}
    if cfg.field == "levelset" or cfg.field == "hashgrid" and cfg.optimizer == "line-search":
        # one index inside the surface: how far from the truth
        row["truth_index"] = float(truth.eta)
        init = json.loads((run / "init.json").read_text()) if (run / "init.json").is_file() else {}
        row["start"]["index"] = init.get("eta")
        if cfg.field == "levelset":
            row["fit"]["index"] = float(fit.params[-1])
        else:  # its eta_max, less the sigmoid's headroom (the index a ramp's eta_max is)
            top = fit.kind.eta_top(cfg, 2.0)
            row["fit"]["index"] = 1 + (fit.eta_max - 1) / (top - 1)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="", help="comma-separated (default: the suite's)")
    ap.add_argument(
        "--suite",
        default="paper",
        choices=["paper", "family", "graded"],
        help="paper: sphere, prism, drop; family: the glass solids of `dataset make`; graded: "
        "the graded development set (luneburg, plume, three blob clusters, the GRIN rod and "
        "lens)",
    )
    ap.add_argument("--views", type=int, default=100, help="views of each dataset")
    ap.add_argument("--res", type=int, default=128, help="image size of the views")
    ap.add_argument("--grid", type=int, default=64, help="grid resolution (voxel or level set)")
    ap.add_argument(
        "--field",
        default="levelset",
        choices=["levelset", "voxel", "hashgrid", "interface", "auto"],
        help="auto: the command line's default, the model its start chooses",
    )
    ap.add_argument("--width", type=float, help="interface width, mm (default: the fit's)")
    ap.add_argument(
        "--ceiling-grids",
        type=lambda v: [int(x) for x in v.split(",") if x],
        default=[],
        metavar="N,N",
        help="also score the truth on these finer grids (the fit's grid-based models): what "
        "the model would hold at each resolution",
    )
    ap.add_argument(
        "--iterations", type=int, help="default: 100 for Adam, the fit's own for a line search"
    )
    ap.add_argument("--batch", type=int, default=8192)
    ap.add_argument("--step", type=float, default=0.0, help="mm; 0: the fit's default")
    ap.add_argument("--lr", type=float, default=None, help="default: the fit's")
    ap.add_argument("--config", default="", help="a fit TOML applied under the flags above")
    ap.add_argument("--data", default="bench_results/data")
    ap.add_argument("--runs", default="bench_results/runs")
    ap.add_argument("--json", default="bench_results/reconstruction.json")
    ap.add_argument("--shard", default="", help="i/n: run every n-th scene from the i-th")
    ap.add_argument("--merge", action="store_true", help="merge the shards' JSON files")
    ap.add_argument("--page", default="", help="also write the table as this Markdown page")
    args = ap.parse_args()

    from clrefract import shards
    from clrefract.family import FAMILY

    graded = ("luneburg", "plume", "blobs:0", "blobs:1", "blobs:2", "grin-rod", "grin-lens")
    suite = {"paper": ("sphere", "prism", "drop"), "family": FAMILY, "graded": graded}[args.suite]
    scenes = [s.strip() for s in args.scenes.split(",")] if args.scenes else list(suite)
    rows = []
    if args.merge:
        rows = shards.merge(args.json, scenes)["scenes"]
    for scene in [] if args.merge else shards.select(scenes, args.shard):
        print(f"== {scene}", file=sys.stderr)
        rows.append(bench_scene(scene, args))
    head = (
        f"{'scene':12} {'model':9} {'PSNR':>6} {'SSIM':>6} {'D_C mm':>7} {'eta RMSE':>9} "
        f"{'index':>6} {'time':>7}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        finer = {f"ceil@{c['grid']}": c for c in r.get("ceilings", [])}
        models = [(k, r[k]) for k in ("empty", "start", "fit", "ceiling")] + list(finer.items())
        for model, m in models:
            if m is None:
                continue
            dc = m.get("chamfer_mm")
            t = m.get("seconds")
            n = r.get("truth_index") if model.startswith("ceil") else m.get("index")
            print(
                f"{r['scene']:12} {model if model != 'fit' else r.get('model', 'fit'):9.9} "
                f"{m['test_psnr']:6.2f} {m['test_ssim']:6.3f} "
                f"{'-' if dc is None else f'{dc:.2f}':>7} {m.get('eta_rmse', float('nan')):9.4f} "
                f"{'-' if n is None else f'{n:.3f}':>6} {'' if t is None else f'{t:6.0f}s':>7}"
            )
    for r in rows:
        for m in r.values():
            if isinstance(m, dict):
                m.pop("views", None)
    out = shards.path_for(args.json, "" if args.merge else args.shard)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"args": vars(args), "scenes": rows}, indent=2))
    print(f"wrote {out}")
    if args.page:
        Path(args.page).write_text(page(rows, args))
        print(f"wrote {args.page}")


def page(rows: list[dict], args) -> str:
    """The table as a Markdown page: test PSNR of the empty box, the start, the fit and the
    ceiling, per scene, with the command that measures it again."""
    devices = sorted({r.get("device", "not recorded") for r in rows})
    cmd = (
        f"python tools/bench_reconstruction.py --suite {args.suite} --field {args.field} "
        + (f"--ceiling-grids {','.join(map(str, grids))} " if (grids := args.ceiling_grids) else "")
        + f"--page {args.page}"
    )
    lines = [
        f"# Reconstruction: the {args.suite} set",
        "",
        "Written by `tools/bench_reconstruction.py --page`; not edited by hand. Measure again "
        "(add `--shard i/n` to n processes, then `--merge --page` once):",
        "",
        f"```bash\n{cmd}\n```",
        "",
        f"- Protocol: {args.views} views of {args.res} x {args.res}, every fifth a test view; "
        f"a {args.grid}^3 grid; the model: `{args.field}`"
        + (" (the command line's default: its start chooses)" if args.field == "auto" else "")
        + ".",
        "- empty: eta = 1 everywhere; start: the fit's start; ceiling: the truth in the fit's "
        "own representation and box (a voxel grid's: its eta sampled on the nodes; a surface's: "
        "its signed distance sampled on the nodes, which a fit that places its own nodes can "
        "pass; a hash grid's: the truth distilled into it).",
        "- Wall: the whole `clrefract fit` (start, model choice, steps, scoring) in seconds; "
        "other work may have shared the cores.",
        f"- Device: {'; '.join(devices)}.",
        "",
        "| scene | model | empty | start | fitted | ceiling | fitted - ceiling | eta RMSE "
        "| best step | wall (s) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        fit, ceil = r["fit"], r.get("ceiling")
        psnr = {k: r[k]["test_psnr"] for k in ("empty", "start", "fit")}
        top = ceil["test_psnr"] if ceil else None
        gap = "-" if top is None else f"{psnr['fit'] - top:+.2f}"
        lines.append(
            f"| {r['scene']} | {r.get('model', r['field'])} | {psnr['empty']:.2f} "
            f"| {psnr['start']:.2f} | **{psnr['fit']:.2f}** "
            f"| {'-' if top is None else f'{top:.2f}'} "
            f"| {gap} "
            f"| {fit.get('eta_rmse', float('nan')):.2g} | {fit.get('best_iteration', '-')} "
            f"| {fit.get('seconds', float('nan')):.0f} |"
        )
    finer = [
        f"{r['scene']} " + ", ".join(f"{c['test_psnr']:.2f} dB at {c['grid']}^3" for c in cs)
        for r in rows
        if (cs := r.get("ceilings"))
    ]
    if finer:
        lines += ["", "The truth on finer grids (the same model, more nodes):", ""]
        lines += [f"- {line}" for line in finer]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
