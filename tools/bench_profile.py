"""Where a fit step's time goes, per field kind: waiting for OpenCL, or host work between
launches (NumPy, Python, argument set-up, the enqueue calls themselves).

    python tools/bench_profile.py [--kinds voxel,levelset,hashgrid,interface] [--views 24]
        [--res 64] [--steps 10] [--warmup 2] [--profile-steps 3] [--threshold 20]
        [--json bench_profile.json]

A small fit per kind on one synthetic sphere, at the kind's own optimiser, then timed steps.
While they run, pyopencl's blocking entry points (`BLOCKING`) are wrapped with timers: the
time inside them is `waited`, the rest of the step is `host`. Kernel launches are timed too
(an enqueue must return at once), and the thread's CPU time outside the waits should make up
the host time: a large `gap` means a blocking call the wrapper missed (or a busy machine).
Kinds whose host share passes --threshold are then run under cProfile. Absolute times on a
shared machine are noise; compare the shares.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import tempfile
import threading
import time
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_trace import print_table  # noqa: E402

KINDS = ("voxel", "levelset", "hashgrid", "interface")
# every pyopencl call in clrefract/ that can block the host on device work (grep of
# clrefract/ for finish, wait and enqueue_copy): queue.finish(), enqueue_copy to or from the
# host with is_blocking (its default), and the two ways to wait for events
BLOCKING = ("CommandQueue.finish", "Event.wait", "wait_for_events", "enqueue_copy")
# the launches: a Kernel called with its queue (clrefract launches no other way)
LAUNCHES = ("Kernel.__call__",)


def _copy_blocks(cl, args, kwargs) -> bool:
    """Whether enqueue_copy(queue, dest, src, ...) waits: to or from the host, is_blocking
    (default True); a copy between two buffers never waits."""
    dest, src = args[1], args[2]
    device = cl.MemoryObjectHolder
    return kwargs.get("is_blocking", True) and not (
        isinstance(dest, device) and isinstance(src, device)
    )


class WaitTimer:
    """While entered, the seconds the entering thread spends blocked in pyopencl (`waited`),
    in kernel launches (`launched`), and its CPU time outside the waits (`cpu`); `calls`
    counts each entry point ("enqueue_copy" only where it blocked, "enqueue_copy (async)"
    where it did not). `step()` measures one step's share of them. Calls from other threads
    and calls nested in a timed call are not counted again."""

    def __init__(self):
        self.waited = self.launched = self.wait_cpu = 0.0
        self.calls: Counter = Counter()
        self._saved: list = []
        self._depth = 0
        self._thread = None

    def __enter__(self) -> WaitTimer:
        import pyopencl as cl

        self._thread = threading.get_ident()
        owners = {"CommandQueue": cl.CommandQueue, "Event": cl.Event, "Kernel": cl.Kernel}
        for name in BLOCKING + LAUNCHES:
            owner_name, _, attr = name.rpartition(".")
            owner = owners[owner_name] if owner_name else cl
            fn = getattr(owner, attr)
            self._saved.append((owner, attr, fn))
            launch = name in LAUNCHES
            blocks = (lambda a, k: _copy_blocks(cl, a, k)) if attr == "enqueue_copy" else None
            setattr(owner, attr, self._wrap(fn, attr, launch, blocks))
        return self

    def __exit__(self, *exc) -> None:
        for owner, attr, fn in reversed(self._saved):
            setattr(owner, attr, fn)
        self._saved.clear()

    def _wrap(self, fn, name: str, launch: bool, blocks):
        import pyopencl as cl

        timer = self

        def timed(*args, **kwargs):
            if timer._depth or threading.get_ident() != timer._thread:
                return fn(*args, **kwargs)
            waits = not launch and (blocks is None or blocks(args, kwargs))
            timer._depth += 1
            c0, t0 = time.thread_time(), time.perf_counter()
            try:
                out = fn(*args, **kwargs)
                if not waits and not launch and isinstance(out, cl.NannyEvent):
                    # pyopencl waits for a copy to or from host memory when its event is
                    # dropped, and clrefract drops every one at once: wait here, timed
                    out.wait()
                    waits, name_ = True, f"{name} (dropped event)"
                else:
                    name_ = name
                return out
            finally:
                dt = time.perf_counter() - t0
                timer._depth -= 1
                if waits:
                    timer.waited += dt
                    timer.wait_cpu += time.thread_time() - c0
                    timer.calls[name_] += 1
                elif launch:
                    timer.launched += dt
                    timer.calls["launch"] += 1
                else:
                    timer.calls[f"{name} (async)"] += 1

        return timed

    def totals(self) -> tuple[float, float, float]:
        return self.waited, self.launched, self.wait_cpu

    @contextmanager
    def step(self):
        """Time the body: yields a dict that, once the body is done, holds wall_s,
        waited_s, host_s (wall less waited), launch_s, cpu_s (the thread's CPU time
        outside waits), launches and gap (1 - (waited + cpu) / wall)."""
        out: dict = {}
        w0, l0, c_in0 = self.totals()
        launches0 = self.calls["launch"]
        c0, t0 = time.thread_time(), time.perf_counter()
        yield out
        wall = time.perf_counter() - t0
        cpu = time.thread_time() - c0
        waited, launched, c_in = (b - a for a, b in zip((w0, l0, c_in0), self.totals()))
        out.update(
            wall_s=wall,
            waited_s=waited,
            host_s=wall - waited,
            launch_s=launched,
            cpu_s=cpu - c_in,
            launches=self.calls["launch"] - launches0,
            gap=1.0 - (waited + cpu - c_in) / wall,
        )


def small_fit(kind: str, dataset: Path, run: Path, overrides: dict):
    """A fit of `kind` at its defaults (its own optimiser), started; the hull's extra
    searches off (they change the start, not the steps)."""
    from clrefract.fit import load_config, prepare_fit

    items = dict(field=kind, seed=0, validate_every=0, tighten_hull=False, shell_starts=False)
    items.update(overrides)
    cfg = load_config(None, items)
    return prepare_fit(dataset, run, cfg, stream=io.StringIO())


def measure(fit, steps: int, warmup: int, timer: WaitTimer) -> list[dict]:
    """Per timed step: its share of the timer, and the rays it traced."""
    for _ in range(warmup):
        fit.step()
    rows = []
    for _ in range(steps):
        with timer.step() as t:
            row = fit.step()
        t["rays"] = int(round(row["rays_per_s"] * row["seconds"]))
        rows.append(t)
    return rows


def summary(kind: str, optimizer: str, steps: list[dict]) -> dict:
    """Median step figures (ms) of one kind."""

    def med(k):
        return float(np.median([s[k] for s in steps]))

    wall, waited = med("wall_s"), float(np.median([s["waited_s"] for s in steps]))
    host = float(np.median([s["host_s"] for s in steps]))
    return {
        "kind": kind,
        "optimizer": optimizer,
        "step_ms": 1e3 * wall,
        "waited_ms": 1e3 * waited,
        "host_ms": 1e3 * host,
        "host_share_pct": 100 * float(np.median([s["host_s"] / s["wall_s"] for s in steps])),
        "launch_ms": 1e3 * med("launch_s"),
        "launches": int(med("launches")),
        "gap_pct": 100 * med("gap"),
        "rays_per_step": int(med("rays")),
        "steps": steps,
    }


def profile(fit, steps: int, top: int) -> list[dict]:
    """cProfile over `steps` steps: the functions of most own time (host work), with their
    own and cumulative ms per step."""
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(steps):
        fit.step()
    prof.disable()
    stats = pstats.Stats(prof)
    rows = []
    for (path, line, name), (_, calls, own, cum, _) in stats.stats.items():
        where = f"{Path(path).name}:{line}" if line else path
        rows.append(
            {
                "function": f"{name} ({where})",
                "calls_per_step": calls / steps,
                "own_ms": 1e3 * own / steps,
                "cumulative_ms": 1e3 * cum / steps,
            }
        )
    rows.sort(key=lambda r: -r["own_ms"])
    return rows[:top]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--res", type=int, default=64, help="pixels across a view")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--profile-steps", type=int, default=3, help="0: no cProfile")
    ap.add_argument("--threshold", type=float, default=20.0, help="host share to profile, %%")
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--dataset", type=Path, help="a dataset to use instead of the sphere")
    ap.add_argument("--json", default="bench_profile.json")
    args = ap.parse_args()
    from clrefract.runtime import default_runtime
    from clrefract.synth import MakeOptions, make_dataset

    kinds = args.kinds.split(",")
    tmp = Path(tempfile.mkdtemp(prefix="bench_profile_"))
    data = args.dataset
    if data is None:
        data = tmp / "sphere"
        make_dataset("sphere", data, MakeOptions(views=args.views, res=args.res, env_width=512))
    info = default_runtime().info
    print(f"device: {info.platform} / {info.name}\n")
    rows, profiles = [], {}
    for kind in kinds:
        t0 = time.perf_counter()
        fit = small_fit(kind, data, tmp / kind, {})
        print(f"{kind}: started in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        with WaitTimer() as timer:
            steps = measure(fit, args.steps, args.warmup, timer)
        row = summary(kind, fit.cfg.optimizer, steps)
        row["calls_per_step"] = {k: v / (args.steps + args.warmup) for k, v in timer.calls.items()}
        rows.append(row)
        if args.profile_steps and row["host_share_pct"] > args.threshold:
            profiles[kind] = profile(fit, args.profile_steps, args.top)
    cols = ["kind", "optimizer", "step_ms", "waited_ms", "host_ms", "host_share_pct"]
    cols += ["rays_per_step", "launches", "launch_ms", "gap_pct"]
    print(f"Median of {args.steps} steps after {args.warmup} ({args.views} views of {args.res}):")
    print_table(rows, cols)
    for kind, prof in profiles.items():
        print(f"\n{kind}: host share above {args.threshold:g}%; cProfile, per step:")
        print_table(prof, ["function", "calls_per_step", "own_ms", "cumulative_ms"])
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    report = {
        "device": info.name,
        "views": args.views,
        "res": args.res,
        "steps": args.steps,
        "warmup": args.warmup,
        "threshold_pct": args.threshold,
        "rows": rows,
        "profiles": profiles,
    }
    out.write_text(json.dumps(report, indent=2))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
