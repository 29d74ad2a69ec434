"""Where a fit step's time goes, per field kind: waiting for OpenCL, or host work between
launches (NumPy, Python, argument set-up, the enqueue calls themselves).

    python tools/bench_profile.py [--kinds voxel,levelset,hashgrid,interface,polytope] [--views 24]
        [--res 64] [--steps 10] [--warmup 2] [--profile-steps 3] [--threshold 20]
        [--json bench_profile.json]

A small fit per kind on one synthetic sphere, at the kind's own optimiser, then timed steps.
While they run, pyopencl's blocking entry points (`BLOCKING`) are wrapped with timers: the
time inside them is `waited`, the rest of the step is `host`. A non-blocking copy to or from
host memory blocks too, as its event is dropped (pyopencl's NannyEvent waits for its copy):
clrefract drops each at once, so the wrapper waits for it there. Kernel launches are timed
(an enqueue must return at once; its CPU time says so where PoCL's threads take the core
from it), and the thread's CPU time outside the waits should make up the host time: a large
`gap` means a blocking call the wrapper missed, or a busy machine. Kinds whose host share
passes --threshold are then run under cProfile. Absolute times on a shared machine are
noise; compare the shares.
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

KINDS = ("voxel", "levelset", "hashgrid", "interface", "polytope")
# every pyopencl call in clrefract/ that can block the host on device work (grep of
# clrefract/ for finish, wait and enqueue_): queue.finish(), enqueue_copy to or from the
# host (blocking, or its event dropped), and the two ways to wait for events. All are
# looked up on the module or the class at each call (runtime.cl is pyopencl itself)
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
    """While entered, pyopencl's blocking calls (BLOCKING) and launches (LAUNCHES) are timed
    on the entering thread: `waited` and `launched` seconds, the thread's CPU time in each
    (`wait_cpu`, `launch_cpu`), and `calls` per entry point ("enqueue_copy" where it blocked,
    "enqueue_copy (dropped event)" where its event's drop did, "... (async)" where nothing
    waited). `step()` gives one step's share. Calls from other threads, and calls inside a
    timed call, are not counted again. Entered again, it goes on adding."""

    def __init__(self):
        self.waited = self.launched = self.wait_cpu = self.launch_cpu = 0.0
        self.calls: Counter = Counter()
        self._saved: list = []
        self._busy = False
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
            wrap = self._launch if name in LAUNCHES else self._wait
            setattr(owner, attr, wrap(fn, attr, cl))
        return self

    def __exit__(self, *exc) -> None:
        for owner, attr, fn in reversed(self._saved):
            setattr(owner, attr, fn)
        self._saved.clear()

    def _mine(self) -> bool:
        return not self._busy and threading.get_ident() == self._thread

    def _clocked(self, fn, args, kwargs, then=None):
        """fn's result, seconds and CPU seconds; `then(result)` runs inside the timing."""
        self._busy = True
        c0, t0 = time.thread_time(), time.perf_counter()
        try:
            out = fn(*args, **kwargs)
            if then is not None:
                then(out)
        finally:
            self._busy = False
        return out, time.perf_counter() - t0, time.thread_time() - c0

    def _wait(self, fn, name: str, cl):
        copy = name == "enqueue_copy"

        def waiting(*args, **kwargs):  # cProfile's name for the time spent waiting
            if not self._mine():
                return fn(*args, **kwargs)
            blocks = not copy or _copy_blocks(cl, args, kwargs)
            dropped = []

            def drop(out):
                # pyopencl waits for a copy to or from host memory as its event is dropped
                # (NannyEvent), and clrefract drops every one at once: wait here, timed
                if not blocks and isinstance(out, cl.NannyEvent):
                    out.wait()
                    dropped.append(out)

            out, dt, cpu = self._clocked(fn, args, kwargs, drop)
            if blocks or dropped:
                self.waited += dt
                self.wait_cpu += cpu
                self.calls[name + (" (dropped event)" if dropped else "")] += 1
            else:
                self.calls[name + " (async)"] += 1
            return out

        return waiting

    def _launch(self, fn, name: str, cl):
        def launching(*args, **kwargs):
            if not self._mine():
                return fn(*args, **kwargs)
            out, dt, cpu = self._clocked(fn, args, kwargs)
            self.launched += dt
            self.launch_cpu += cpu
            self.calls["launch"] += 1
            return out

        return launching

    def totals(self) -> tuple:
        return self.waited, self.launched, self.wait_cpu, self.launch_cpu, self.calls["launch"]

    @contextmanager
    def step(self):
        """Time the body: yields a dict that, once the body is done, holds wall_s, waited_s,
        host_s (wall less waited), launch_s and launch_cpu_s (the enqueues, host work),
        cpu_s (the thread's CPU time outside the waits), launches, and gap: 1 - (waited +
        cpu) / wall, the time the thread neither waited in a timed call nor ran (a wait
        missed, or a busy machine)."""
        out: dict = {}
        before = self.totals()
        c0, t0 = time.thread_time(), time.perf_counter()
        yield out
        wall = time.perf_counter() - t0
        cpu = time.thread_time() - c0
        waited, launched, wait_cpu, launch_cpu, launches = (
            b - a for a, b in zip(before, self.totals())
        )
        out.update(
            wall_s=wall,
            waited_s=waited,
            host_s=wall - waited,
            launch_s=launched,
            launch_cpu_s=launch_cpu,
            cpu_s=cpu - wait_cpu,
            launches=launches,
            gap=1.0 - (waited + cpu - wait_cpu) / wall,
        )


def small_fit(kind: str, dataset: Path, run: Path, **overrides):
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

    return {
        "kind": kind,
        "optimizer": optimizer,
        "step_ms": 1e3 * med("wall_s"),
        "waited_ms": 1e3 * med("waited_s"),
        "host_ms": 1e3 * med("host_s"),
        "host_share_pct": 100 * float(np.median([s["host_s"] / s["wall_s"] for s in steps])),
        "launch_ms": 1e3 * med("launch_s"),
        "launch_cpu_ms": 1e3 * med("launch_cpu_s"),
        "cpu_ms": 1e3 * med("cpu_s"),
        "launches": int(med("launches")),
        "gap_pct": 100 * med("gap"),
        "rays_per_step": int(med("rays")),
        "steps": steps,
    }


def profile(fit, steps: int, top: int) -> list[dict]:
    """cProfile over `steps` steps, pyopencl timed as in `measure` (the rows "waiting" and
    "launching" hold the time inside its calls): the functions of most own time, with
    their own and cumulative ms per step."""
    prof = cProfile.Profile()
    with WaitTimer():
        prof.enable()
        for _ in range(steps):
            fit.step()
        prof.disable()
    rows = []
    for (path, line, name), (_, calls, own, cum, _) in pstats.Stats(prof).stats.items():
        where = f"{Path(path).name}:{line}" if line else path
        if path == __file__ and name in ("waiting", "launching"):
            name, where = f"{name} (pyopencl, timed)", "bench_profile.py"
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

    info = default_runtime().info
    print(f"device: {info.platform} / {info.name}\n")
    with tempfile.TemporaryDirectory(prefix="bench_profile_") as tmp:
        rows, profiles = run_kinds(args, Path(tmp))
    cols = ["kind", "optimizer", "step_ms", "waited_ms", "host_ms", "host_share_pct"]
    cols += ["rays_per_step", "launches", "launch_ms", "launch_cpu_ms", "cpu_ms", "gap_pct"]
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


def run_kinds(args, tmp: Path) -> tuple[list[dict], dict]:
    """The rows of each kind, and the cProfile rows of those above the threshold."""
    from clrefract.synth import MakeOptions, make_dataset

    data = args.dataset
    if data is None:
        data = tmp / "sphere"
        make_dataset("sphere", data, MakeOptions(views=args.views, res=args.res))
    rows, profiles = [], {}
    for kind in args.kinds.split(","):
        t0 = time.perf_counter()
        fit = small_fit(kind, data, tmp / kind)
        start = time.perf_counter() - t0
        print(f"{kind}: started in {start:.1f} s", file=sys.stderr)
        with WaitTimer() as timer:
            steps = measure(fit, args.steps, args.warmup, timer)
        row = summary(kind, fit.cfg.optimizer, steps)
        row["start_s"] = start
        row["calls_per_step"] = {k: v / (args.steps + args.warmup) for k, v in timer.calls.items()}
        rows.append(row)
        if args.profile_steps and row["host_share_pct"] > args.threshold:
            profiles[kind] = profile(fit, args.profile_steps, args.top)
    return rows, profiles


if __name__ == "__main__":
    main()
