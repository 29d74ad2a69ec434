"""The paper's Table 1, measured: every method on every scene under a named protocol.

A protocol fixes the datasets (views, image size) and each method's budget. Jobs are the
(scene, method) pairs in a fixed order; `--shard i/n` takes every n-th of them from the i-th
(0-based), so machines split a protocol without talking; each shard writes its records to
shard-i-of-n.json and `merge` joins the shards' records into the table. A job whose run folder
already holds eval/eval.json is not run again (a shard that stopped can be started again).

Outputs: table.md (readable: the mean over scenes beside the paper's figures, then each scene),
table.csv and table.json (one record per run); on request the results page (docs/results.md:
how, where and when it was measured, one table per figure) with its records beside it.
"""

from __future__ import annotations

import csv
import io
import json
import math
import shlex
import sys
import time
from pathlib import Path

from . import shards
from .baselines.methods import METHODS, run_method
from .errors import ClrefractError
from .family import FAMILY

SCENES = ("sphere", "prism", "drop")

# Budgets. tiny: a smoke test of the whole pipeline (minutes, meaningless scores). quick: the
# issue's 128 x 128 protocol, sized for about 90 minutes for the paper's twelve runs on 2 CPU cores
# from costs measured on the sphere with the machine shared (load 7.5, 2026-11-23): dataset
# 18 s; grid start 147 s then 1.0 s per step of 8192 rays; synapse about 1 s per step; meridian
# (the neural field) 0.6 s per step, 360 s for its 600 on the sphere (load 4, niced; the 48^3
# grid stand-in took 0.3 s). Not yet timed end to end. standard: 256 x 256 and four times the
# iterations. full: the paper's 800 x 800 and 20,000 iterations, for GPUs. The interface row
# (not the paper's; issue 57) runs its kind's defaults beside them, each fit meant to take at
# most 10 minutes on 2 cores (not yet timed end to end).
# the tiny protocol's interface and default rows: a 16^3 grid, none of the hull's extra shapes
TINY_CURVED = dict(
    res=16, iterations=10, batch=2048, validate_every=5, tighten_hull=False, shell_starts=False
)
PROTOCOLS: dict[str, dict] = {
    "tiny": {
        "data": dict(views=12, res=32, env_width=512, volume_res=16),
        "eval": dict(samples=20000),  # chamfer samples per side (the protocol's 100k elsewhere)
        "methods": {
            "grid": dict(res=16, iterations=10, batch=2048, validate_every=5),
            "meridian": dict(
                iterations=20, batch=2048, levels=4, log2_table=12, n_max=32, surface_res=32
            ),
            "synapse": dict(res=24, iterations=20, batch=2048),
            "vertexnet": dict(
                iterations=10, batch=2048, levels=4, log2_table=12, distil_iterations=50
            ),
            "interface": TINY_CURVED,
            "auto": TINY_CURVED,
        },
    },
    "quick": {
        "data": dict(views=100, res=128),
        "methods": {
            # 1 mm, not the voxel fit's default half cell (0.39 mm at 128^3): 2.5x the steps
            # would break the 90 minutes, for 0.33 to 0.44 dB on the sphere (bench_voxel_step)
            "grid": dict(iterations=300, batch=8192, step=1.0),
            "meridian": dict(iterations=600, batch=8192),
            # 128^3 x 4 values: about 1 s per step on 2 busy cores (the backward's atomics)
            "synapse": dict(iterations=300, batch=8192),
            # the hash grid's own defaults: 16 line-search steps of about 28 s at a 0.5 mm
            # interface, about 14 minutes a scene alone on 2 cores (Adam's 100 steps of 4 s
            # kept the start's parameters or crept from them)
            "vertexnet": dict(batch=8192),
            # the interface kind's own defaults (kinds.INTERFACE_DEFAULTS: its descent's steps)
            "interface": dict(batch=8192),
            "auto": dict(batch=8192),  # each candidate's own defaults
        },
    },
    "standard": {
        "data": dict(views=100, res=256),
        "methods": {
            "grid": dict(iterations=1200, batch=16384),
            "meridian": dict(iterations=2400, batch=16384),
            "synapse": dict(iterations=2400, batch=16384),
            "vertexnet": dict(batch=16384),  # its line search's own count of steps
            "interface": dict(iterations=1200, batch=16384),
            "auto": dict(batch=16384),
        },
    },
    "full": {
        "data": dict(views=100, res=800),
        "methods": {
            **{m: dict(iterations=20000, batch=65536) for m in METHODS},
            "vertexnet": dict(batch=65536),  # its line search's own count of steps
        },
    },
}


def jobs(scenes, methods, shard: str = "", family_methods=()) -> list[tuple[str, str]]:
    """The (scene, method) runs of a shard ('i/n', as shards.parse reads it): every method on
    every scene, then the family methods on each solid of the family (the development set)."""
    every = [(s, m) for s in scenes for m in methods]
    every += [(s, m) for s in FAMILY for m in family_methods if (s, m) not in every]
    return shards.select(every, shard)


def dataset_for(protocol: str, scene: str, data_root: Path) -> Path:
    """The protocol's dataset of a scene, made once and then reused."""
    from .synth import MakeOptions, make_dataset

    out = data_root / protocol / scene
    if not (out / "scene.json").is_file():
        make_dataset(scene, out, MakeOptions(**PROTOCOLS[protocol]["data"]))
    return out


def run_job(protocol: str, scene: str, method: str, out: Path, data_root: Path, stream=None):
    """Train and score one method on one scene; the record of the run."""
    from .evaluate import evaluate_run

    run = out / "runs" / f"{scene}-{method}"
    done = run / "eval" / "eval.json"
    wall_file = run / "wall.json"
    if done.is_file() and wall_file.is_file():
        scores, wall = json.loads(done.read_text()), json.loads(wall_file.read_text())
    else:
        data = dataset_for(protocol, scene, data_root)
        if run.exists():  # an unfinished earlier attempt: start it afresh
            import shutil

            shutil.rmtree(run)
        wall = run_method(method, data, run, PROTOCOLS[protocol]["methods"][method], stream)
        wall.update(_measured_on(run))
        wall_file.write_text(json.dumps(wall))
        t0 = time.perf_counter()
        scores = evaluate_run(run, **PROTOCOLS[protocol].get("eval", {}))
        wall["eval_seconds"] = time.perf_counter() - t0
        wall_file.write_text(json.dumps(wall))
    m = METHODS[method]
    paper = m.paper or (None, None, None)  # a row the paper does not have
    return {
        "protocol": protocol,
        "scene": scene,
        "method": method,
        "paper_name": m.paper_name,
        "psnr": scores["psnr"],
        "ssim": scores["ssim"],
        "chamfer_mm": scores["chamfer_mm"],
        "eta_rmse": scores["eta_rmse"],
        "wall_seconds": wall["wall_seconds"],
        "paper_psnr": paper[0],
        "paper_ssim": paper[1],
        "paper_chamfer_mm": paper[2],
        "run": str(run),
        # where and when it was measured (None in runs that predate these keys)
        **{k: wall.get(k) for k in ("eval_seconds", *MEASURED_ON)},
    }


MEASURED_ON = ("commit", "commit_dirty", "device", "driver", "ended")


def _measured_on(run: Path) -> dict:
    """The commit, OpenCL device and driver a run was trained with, and when it ended (UTC):
    from its run.json, else (the straight-ray runs record none) this process's."""
    from .provenance import git_state, now

    try:
        meta = json.loads((run / "run.json").read_text())
    except (OSError, ValueError):
        meta = {}
    commit, dirty = git_state()
    out = {"commit": meta.get("commit", commit), "commit_dirty": meta.get("commit_dirty", dirty)}
    out["device"], out["driver"] = meta.get("device"), meta.get("driver")
    if out["device"] is None:  # the device Runtime(None) picks, as the run's did
        from .runtime import pick_device

        info, _ = pick_device(None)
        out["device"], out["driver"] = info.name, f"{info.platform} {info.driver_version}"
    return {**out, "ended": now()}


def run_protocol(
    protocol: str,
    out: Path,
    shard: str = "",
    scenes=SCENES,
    methods=tuple(METHODS),
    data_root: Path | None = None,
    stream=None,
    family_methods=(),
) -> list[dict]:
    if protocol not in PROTOCOLS:
        raise ClrefractError(f"unknown protocol {protocol!r}; protocols: {', '.join(PROTOCOLS)}")
    bad = [m for m in (*methods, *family_methods) if m not in METHODS]
    if bad:
        raise ClrefractError(f"unknown method(s) {bad}; methods: {', '.join(METHODS)}")
    out.mkdir(parents=True, exist_ok=True)
    data_root = data_root or out / "data"
    records = []
    i, n = shards.parse(shard)
    path = out / f"shard-{i}-of-{n}.json"
    for scene, method in jobs(scenes, methods, shard, family_methods):
        print(f"table: {protocol} {scene} {method}", file=stream or sys.stderr)
        records.append(run_job(protocol, scene, method, out, data_root, stream))
        path.write_text(json.dumps(records, indent=2))  # after each run: a stop loses one
    return records


def merge(folders: list[Path]) -> list[dict]:
    """Records of every shard file in the folders, one per (protocol, scene, method)."""
    seen: dict[tuple, dict] = {}
    for f in folders:
        for path in sorted(Path(f).glob("shard-*-of-*.json")):
            for r in json.loads(path.read_text()):
                seen[(r["protocol"], r["scene"], r["method"])] = r
    if not seen:
        raise ClrefractError(f"no shard-*-of-*.json in {', '.join(map(str, folders))}")
    order = {m: k for k, m in enumerate(METHODS)}
    return sorted(seen.values(), key=lambda r: (r["scene"], order.get(r["method"], 99)))


def _num(x) -> float | None:
    return x if isinstance(x, int | float) and x is not None and math.isfinite(x) else None


def _mean(rows, key):
    vals = [_num(r[key]) for r in rows]
    return None if not vals or any(v is None for v in vals) else sum(vals) / len(vals)


def _f(x, digits):
    if isinstance(x, str):
        return x
    return "-" if _num(x) is None else f"{x:.{digits}f}"


def _paper(x, digits):
    """The paper's figure in brackets after ours; nothing for a row the paper lacks."""
    return "" if _num(x) is None else f" ({x:.{digits}f})"


def markdown(records: list[dict]) -> str:
    protocol = records[0]["protocol"]
    scenes = sorted({r["scene"] for r in records})
    lines = [
        f"## Table 1, measured ({protocol} protocol; scenes: {', '.join(scenes)})",
        "",
        "Mean over scenes; the paper's figures (its own benchmark, 800 x 800) in brackets "
        "(none for the interface model, which the paper does not have). "
        "A dash: missing on some scene.",
        "",
        "| Method | PSNR | SSIM | D_C (mm) | eta RMSE | wall time (s) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for method in METHODS:
        rows = [r for r in records if r["method"] == method]
        if not rows:
            continue
        r0 = rows[0]
        eta = "n/a" if all(r["eta_rmse"] == "n/a" for r in rows) else _f(_mean(rows, "eta_rmse"), 4)
        lines.append(
            f"| {r0['paper_name']} | {_f(_mean(rows, 'psnr'), 2)}{_paper(r0['paper_psnr'], 2)} "
            f"| {_f(_mean(rows, 'ssim'), 3)}{_paper(r0['paper_ssim'], 3)} "
            f"| {_f(_mean(rows, 'chamfer_mm'), 2)}{_paper(r0['paper_chamfer_mm'], 2)} "
            f"| {eta} | {sum(r['wall_seconds'] for r in rows):.0f} |"
        )
    lines += [
        "",
        "### Per scene",
        "",
        "| Scene | Method | PSNR | SSIM | D_C (mm) | eta RMSE | wall time (s) |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in records:
        lines.append(
            f"| {r['scene']} | {r['paper_name']} | {_f(r['psnr'], 2)} | {_f(r['ssim'], 3)} "
            f"| {_f(r['chamfer_mm'], 2)} | {_f(r['eta_rmse'], 4)} | {r['wall_seconds']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def write_table(records: list[dict], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.md").write_text(markdown(records))
    (out / "table.json").write_text(json.dumps(records, indent=2))
    buf = io.StringIO()
    # every record's keys (merged shards of older versions may lack some)
    w = csv.DictWriter(buf, fieldnames=list({k: 0 for r in records for k in r}))
    w.writeheader()
    w.writerows(records)
    (out / "table.csv").write_text(buf.getvalue())


# The results page (docs/results.md): the table as measured, one table per figure, and what,
# how, where and when it measured. Written from the records alone (saved beside the page), so
# `clrefract table page` writes it again without running anything.
FIGURES = (  # record key, heading, digits, the paper's figure's key
    ("psnr", "PSNR (dB, test views)", 2, "paper_psnr"),
    ("ssim", "SSIM (test views)", 3, "paper_ssim"),
    ("chamfer_mm", "Chamfer distance D_C (mm)", 2, "paper_chamfer_mm"),
    ("eta_rmse", "eta RMSE over the box", 4, None),
    ("wall_seconds", "Wall time of training, start included (s)", 0, None),
)
PROTOCOL_NOTES = {
    "tiny": "a smoke test of the pipeline; its scores mean nothing",
    "quick": "the issue's 128 x 128 protocol, sized for 2 CPU cores",
    "standard": "four times the quick protocol's iterations",
    "full": "the paper's image size and iterations, for GPUs",
}
QUICK_TIME = "an estimated 2 hours on 2 CPU cores"  # PROTOCOLS: ~90 min + 3 interface fits


def _ordered(records, key, order) -> list[str]:
    have = {r[key] for r in records}
    return [x for x in order if x in have] + sorted(have - set(order))


def _split(records) -> tuple[list[dict], list[dict]]:
    """Table 1's records, and those of the family's solids where they are the whole family
    under each of their methods (what `--family-methods` runs); else every record is Table 1's."""
    family = [r for r in records if r["scene"] in FAMILY]
    methods = {r["method"] for r in family}
    if {(r["scene"], r["method"]) for r in family} != {(s, m) for s in FAMILY for m in methods}:
        return records, []
    return [r for r in records if r["scene"] not in FAMILY], family


def page_command(records: list[dict], page: str | Path, readme: str | Path | None = None) -> str:
    """The command line that measures the records' table again and writes the page."""
    protocol = records[0]["protocol"]
    cmd = ["clrefract", "table", "run", "--protocol", protocol, "--out", f"table/{protocol}"]
    table1, family = _split(records)
    scenes, methods = _ordered(table1, "scene", SCENES), _ordered(table1, "method", METHODS)
    if scenes != list(SCENES):
        cmd += ["--scenes", ",".join(scenes)]
    if methods != list(METHODS):
        cmd += ["--methods", ",".join(methods)]
    if family:
        cmd += ["--family-methods", ",".join(_ordered(family, "method", METHODS))]
    cmd += ["--page", str(page)]
    return shlex.join(cmd + (["--readme", str(readme)] if readme else []))


def _distinct(values, none="unknown (runs that predate the record)") -> str:
    seen = list(dict.fromkeys(v for v in values if v is not None))
    return "; ".join(seen) if seen else none


def _settings(d: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in d.items()) or "its defaults"


def _figure_table(records, key, digits, paper_key) -> list[str]:
    """One figure of Table 1: a row per method, a column per scene, their mean, the paper's."""
    scenes, methods = _ordered(records, "scene", SCENES), _ordered(records, "method", METHODS)
    cell = {(r["scene"], r["method"]): r for r in records}
    head = ["Method", *scenes, "mean", *(["paper"] if paper_key else [])]
    lines = ["| " + " | ".join(head) + " |", "|---" + "|---:" * (len(head) - 1) + "|"]
    for m in methods:
        rows = [cell[s, m] for s in scenes if (s, m) in cell]
        mean = "n/a" if all(r[key] == "n/a" for r in rows) else _mean(rows, key)
        if len(rows) < len(scenes):
            mean = None
        row = [f"{rows[0]['paper_name']} (`{m}`)"]
        row += [_f(cell[s, m][key] if (s, m) in cell else None, digits) for s in scenes]
        row.append(_f(mean, digits))
        if paper_key:
            paper = rows[0][paper_key]
            row.append("" if _num(paper) is None else _f(paper, digits))
        lines.append("| " + " | ".join(row) + " |")
    return lines


def _family_table(records) -> list[str]:
    """The family's solids, a row per (solid, method), then each method's mean."""
    head = ["Solid", "Method", "PSNR (dB)", "SSIM", "D_C (mm)", "eta RMSE", "wall time (s)"]
    lines = ["| " + " | ".join(head) + " |", "|---|---" + "|---:" * (len(head) - 2) + "|"]
    for m in _ordered(records, "method", METHODS):
        rows = [r for r in records if r["method"] == m]
        for r in [*sorted(rows, key=lambda r: FAMILY.index(r["scene"])), None]:
            name = "mean" if r is None else r["scene"]
            figures = [_mean(rows, k) if r is None else r[k] for k, *_ in FIGURES]
            cells = [_f(v, d) for v, (_, _, d, _) in zip(figures, FIGURES)]
            lines.append(f"| {name} | `{m}` | " + " | ".join(cells) + " |")
    return lines


def page(records: list[dict], path: str | Path, readme: str | Path | None = None) -> str:
    """The results page of one protocol's records; `path` is where it is written (the commands
    it shows name it, and its records beside it, PATH with .json), `readme` the README whose
    results at a glance the command writes too."""
    protocols = sorted({r["protocol"] for r in records})
    if len(protocols) != 1:
        raise ClrefractError(f"records of protocols {', '.join(protocols)}: a page shows one")
    (protocol,) = protocols
    table1, family = _split(records)
    scenes, methods = _ordered(table1, "scene", SCENES), _ordered(table1, "method", METHODS)
    family_methods = _ordered(family, "method", METHODS)
    spec = PROTOCOLS.get(protocol, {"data": {}, "methods": {}})
    saved = Path(path).with_suffix(".json")
    ended = sorted(r["ended"][:16].replace("T", " ") for r in records if r.get("ended"))
    when = None
    if ended:  # the last one's date only where it is not the first one's
        when = f"{ended[0]} to {ended[-1].removeprefix(ended[0][:11])} UTC"
    commits = [
        None
        if r.get("commit") is None
        else r["commit"][:12] + (" with uncommitted changes" if r.get("commit_dirty") else "")
        for r in records
    ]
    evals = [r.get("eval_seconds") for r in records]
    data = spec["data"]
    lines = [
        "# Results: the paper's Table 1, measured",
        "",
        f"Written by `clrefract table` from its records, [{saved.name}]({saved.name}); "
        "not edited by hand.",
        "",
    ]
    if protocol == "tiny":
        lines += [
            "**Not Table 1's figures: the `tiny` protocol is a smoke test of the pipeline and its "
            f"scores mean nothing.** The quick protocol's page ({QUICK_TIME}):",
            "",
            "```bash",
            page_command([{**r, "protocol": "quick"} for r in records], path, readme),
            "```",
            "",
        ]
    runs = f"- Runs: {len(records)}"
    if table1:
        runs += (
            f"; {len(methods)} methods ({', '.join(methods)}) on {len(scenes)} scenes "
            f"({', '.join(scenes)})"
        )
    if family:
        runs += (
            f"; {', '.join(family_methods)} on the family of {len(FAMILY)} glass solids "
            f"({', '.join(FAMILY)}), the development set"
        )
    lines += [
        runs + ".",
        f"- Protocol: `{protocol}` ({PROTOCOL_NOTES.get(protocol, 'not one of this version')}): "
        f"datasets of {_settings(data)}; every fifth view a test view.",
        "- Budgets: "
        + "; ".join(
            f"{m} ({_settings(spec['methods'].get(m, {}))})"
            for m in _ordered(records, "method", METHODS)
        )
        + ".",
        f"- Scoring: `clrefract eval` ({_settings(spec.get('eval', {}))}).",
        f"- Measured: runs ended {when or _distinct([])}.",
        f"- Commit: {_distinct(commits)}.",
        f"- Device: {_distinct(r.get('device') for r in records)}; driver: "
        f"{_distinct(r.get('driver') for r in records)}.",
        f"- Wall time: training {sum(r['wall_seconds'] for r in records):.0f} s, scoring "
        + (f"{sum(evals):.0f} s" if None not in evals else "unknown")
        + f", over the {len(records)} runs.",
        "- paper: the paper's Table 1 (its own benchmark, 800 x 800, the mean over its scenes); "
        "blank for a row the paper does not have. A dash: no figure.",
        "",
        "Measure again and write this page:",
        "",
        "```bash",
        page_command(records, path, readme),
        "```",
        "",
        "Write this page again from its records, running nothing:",
        "",
        "```bash",
        shlex.join(
            ["clrefract", "table", "page", str(saved), "--out", str(path)]
            + (["--readme", str(readme)] if readme else [])
        ),
        "```",
    ]
    if table1:
        for key, heading, digits, paper_key in FIGURES:
            lines += ["", f"## {heading}", "", *_figure_table(table1, key, digits, paper_key)]
    if family:
        lines += [
            "",
            "## The family of glass solids",
            "",
            "The development set of `clrefract dataset make` (index 1.5; "
            "[evaluation.md](evaluation.md)), each method at the protocol's budget.",
            "",
            *_family_table(family),
        ]
    return "\n".join(lines) + "\n"


# README.md's results at a glance: written between these lines by `--readme`.
GLANCE_BEGIN = "<!-- results at a glance: written by `clrefract table --readme`, not by hand -->"
GLANCE_END = "<!-- end of the results at a glance -->"


def glance(records: list[dict], page_path: str | Path) -> str:
    """The README's summary of a results page: Table 1's PSNR and the family's."""
    table1, family = _split(records)
    ended = sorted(r["ended"][:10] for r in records if r.get("ended"))
    lines = [
        f"PSNR (dB) on the held-out views, `{records[0]['protocol']}` protocol"
        + (f", measured {ended[0]}" if ended else "")
        + (f" to {ended[-1]}" if ended and ended[-1] != ended[0] else "")
        + f"; [{Path(page_path).name}]({page_path}) has SSIM, the chamfer distance, eta, "
        "the wall times and how it was measured.",
        "",
    ]
    if table1:
        lines += _figure_table(table1, "psnr", 2, "paper_psnr")
    for m in _ordered(family, "method", METHODS):
        rows = [r for r in family if r["method"] == m]
        psnr = [r["psnr"] for r in rows]
        lines += [
            "",
            f"The family of {len(FAMILY)} glass solids (the development set), `{m}`: "
            f"{_f(_mean(rows, 'psnr'), 2)} dB on average "
            f"({_f(min(psnr), 2)} to {_f(max(psnr), 2)}).",
        ]
    return "\n".join(lines) + "\n"


def write_glance(readme: str | Path, records: list[dict], page_path: str | Path) -> None:
    """Replace the results at a glance in `readme` (between GLANCE_BEGIN and GLANCE_END)."""
    readme = Path(readme)
    try:
        text = readme.read_text()
    except OSError as exc:
        raise ClrefractError(f"{readme}: cannot read it ({exc.strerror})") from None
    head, sep, rest = text.partition(GLANCE_BEGIN + "\n")
    _, sep2, tail = rest.partition(GLANCE_END)
    if not (sep and sep2):
        raise ClrefractError(f"{readme}: no lines {GLANCE_BEGIN!r} ... {GLANCE_END!r}")
    readme.write_text(head + sep + glance(records, page_path) + sep2 + tail)


def write_page(records: list[dict], path: str | Path, readme: str | Path | None = None) -> None:
    """The results page at `path` and its records beside it (PATH with .json); with `readme`,
    its results at a glance too."""
    path = Path(path)
    if path.suffix == ".json":
        raise ClrefractError(f"{path}: the page is markdown; its records go beside it as .json")
    if readme:  # first: a README without the markers leaves nothing half written
        home = Path(readme).parent
        write_glance(readme, records, path.relative_to(home) if path.is_relative_to(home) else path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.with_suffix(".json").write_text(json.dumps(records, indent=2) + "\n")
    path.write_text(page(records, path, readme))


def read_records(path: str | Path) -> list[dict]:
    """The records of a saved table (table.json, or a page's .json)."""
    try:
        records = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ClrefractError(f"{path}: cannot read the table's records ({exc})") from None
    if not isinstance(records, list) or not records or not all("method" in r for r in records):
        raise ClrefractError(f"{path}: not a table's records (a list of one record per run)")
    return records
