"""Kernel build times per driver and kernel family: first build (empty caches) and cached build
(the driver's or pyopencl's cache from the first), each in a fresh process, as a user sees them.

    python tools/bench_build.py [--device P:D ...] [--json bench_results/build.json]

Without --device every visible device is measured; devices whose driver cannot build the
kernels are listed with the reason. Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FAMILIES = {
    "trace sphere": "trace:sphere",
    "trace + adjoint voxel bspline": "adjoint:voxel",
    "trace + adjoint level set": "adjoint:levelset",
    "trace + adjoint hash grid": "adjoint:hashgrid",
    "snell ground truth": "snell",
}


def _field(kind: str):
    import numpy as np

    from clrefract.fields import field_from_spec
    from clrefract.fields.base import Box
    from clrefract.fields.hashgrid import HashGridConfig, HashGridField
    from clrefract.fields.levelset import LevelSetField
    from clrefract.fields.voxel import VoxelGrid

    box = Box()
    g = np.linspace(-50, 50, 32)
    r = np.sqrt(sum(a**2 for a in np.meshgrid(g, g, g, indexing="ij")))
    if kind == "voxel":
        return VoxelGrid(1 + 0.3 * np.exp(-((r / 18) ** 2)), box, interp="bspline")
    if kind == "levelset":
        return LevelSetField(r - 20, box)
    if kind == "hashgrid":
        return HashGridField(HashGridConfig(levels=8, log2_table=16, hidden=32), box)
    return field_from_spec(kind)


def _child(device: str, family: str, lanes: int | None) -> None:
    """Build one family in this process, run it once on a few rays (PoCL finishes code
    generation at the first launch), and print the seconds as JSON."""
    import numpy as np

    from clrefract.envmap import EnvMap
    from clrefract.fields.base import Box
    from clrefract.gradient import GradientEngine
    from clrefract.runtime import Runtime
    from clrefract.snell import SnellRenderer
    from clrefract.tracer import TraceSettings

    rt = Runtime(device)
    what, _, kind = family.partition(":")
    o = np.tile([0.0, 0.0, -120.0], (64, 1))
    d = np.column_stack([np.linspace(-0.2, 0.2, 64), np.zeros(64), np.ones(64)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t0 = time.perf_counter()
    if what == "snell":
        SnellRenderer(_field("sphere"), runtime=rt).trace(o, d)
        used = 1
    elif what == "trace":
        from clrefract.tracer import Tracer

        tr = Tracer(_field(kind), settings=TraceSettings(lanes=lanes), runtime=rt)
        tr.trace(o, d)
        used = tr.lanes
    else:
        eng = GradientEngine(_field(kind), Box(), TraceSettings(lanes=lanes), runtime=rt)
        eng.loss_and_grad(o, d, np.full((64, 3), 0.3), EnvMap.procedural(64, 32))
        used = eng.tracer.lanes
    seconds = sum(rt.build_seconds.values())
    print(json.dumps({"build_s": seconds, "ready_s": time.perf_counter() - t0, "lanes": used}))


def _run_child(device, family, lanes, cache: Path) -> dict:
    env = dict(os.environ)
    # every cache a driver or pyopencl may use, under one folder per measurement
    env.update(
        XDG_CACHE_HOME=str(cache),
        POCL_CACHE_DIR=str(cache / "pocl"),
        CUDA_CACHE_PATH=str(cache / "nv"),
        CLREFRACT_CACHE_DIR=str(Path.home() / ".cache" / "clrefract"),  # keep the lane probe
    )
    cmd = [sys.executable, __file__, "--child", device, family, str(lanes or 0)]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1200)
    if p.returncode != 0:
        tail = (p.stderr.strip().splitlines() or ["?"])[-1]
        return {"error": f"exit {p.returncode}: {tail[:160]}"}
    return json.loads(p.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", action="append", help="P:D (repeatable); default: all")
    ap.add_argument("--lanes", type=int, default=None, help="default: the device's choice")
    ap.add_argument("--json", default="bench_results/build.json")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        dev, fam, lanes = args.child
        _child(dev, fam, int(lanes) or None)
        return 0

    from clrefract.probe import lane_report, why_unusable
    from clrefract.runtime import list_devices

    infos = list_devices()
    chosen = [i for i in infos if not args.device or i.selector in args.device]
    rows = []
    for info in chosen:
        rep = lane_report(info, "float32")
        if not rep["widths"]:
            rows.append({"device": info.driver, "family": "(all)", "error": why_unusable(rep)})
            continue
        for name, fam in FAMILIES.items():
            with tempfile.TemporaryDirectory() as tmp:
                first = _run_child(info.selector, fam, args.lanes, Path(tmp))
                cached = _run_child(info.selector, fam, args.lanes, Path(tmp))
            rows.append({"device": info.driver, "family": name, "first": first, "cached": cached})
    print("build: clBuildProgram; ready: build and the first run on 64 rays (seconds)")
    print(
        f"{'driver':58} {'kernel family':30} {'lanes':>5} {'first: build':>12} "
        f"{'ready':>6} {'cached: build':>13} {'ready':>6}"
    )
    for r in rows:
        if "error" in r:
            print(f"{r['device'][:58]:58} {r['family']:30} {'':>5} cannot build: {r['error']}")
            continue
        f, c = r["first"], r["cached"]
        if "error" in f or "error" in c:
            print(f"{r['device'][:58]:58} {r['family']:30} {f.get('error') or c.get('error')}")
            continue
        print(
            f"{r['device'][:58]:58} {r['family']:30} {f['lanes']:5d} {f['build_s']:12.2f} "
            f"{f['ready_s']:6.2f} {c['build_s']:13.2f} {c['ready_s']:6.2f}"
        )
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
