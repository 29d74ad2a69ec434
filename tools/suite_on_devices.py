"""The test suite on every OpenCL device this machine has (or those named), file by file, and
a table of device against pass / fail.

Each test file runs in its own pytest process with PYOPENCL_CTX naming the device, under a
time limit, so one stalling file costs only itself. Files run `--jobs` at a time.

    python tools/suite_on_devices.py [--devices 0:0 1:0] [--jobs 2] [--timeout 900] [--budget S]
                                     [--json bench_results/suite_on_devices.json] [tests/...]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

from clrefract.limits import host_cores
from clrefract.runtime import list_devices

ROOT = Path(__file__).resolve().parents[1]
COUNTS = re.compile(r"(\d+) (passed|failed|errors?|skipped|xfailed|xpassed|deselected)")


def run_file(path: str, selector: str, timeout: float, deadline: float, args=(), env=None) -> dict:
    """One pytest process over `path` (and the pytest `args`) on device `selector`, with
    `env` added to this process's environment; its counts, failures and whole output."""
    env = dict(os.environ, **(env or {}), PYOPENCL_CTX=selector, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "pytest", "-q", "-rfE", "-p", "no:cacheprovider", path, *args]
    t0 = time.perf_counter()
    # a file queued behind slow ones gets what is left of the whole run's budget
    timeout = max(1.0, min(timeout, deadline - t0))
    try:
        done = subprocess.run(
            cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout
        )
        out, rc = done.stdout + done.stderr, done.returncode
        # pytest's summary ends its stdout; a driver may write to stderr after it
        tail = done.stdout.strip().splitlines()[-1:]
    except subprocess.TimeoutExpired as exc:  # its output may come as bytes despite text=True
        parts = [exc.stdout or "", exc.stderr or ""]
        out = "".join(p.decode(errors="replace") if isinstance(p, bytes) else p for p in parts)
        rc, tail = None, []
    counts = {"passed": 0, "failed": 0, "errors": 0, "skipped": 0}
    for n, what in COUNTS.findall(tail[0] if tail else ""):
        key = "errors" if what.startswith("error") else what
        if key in counts:
            counts[key] += int(n)
    failures = [ln for ln in out.splitlines() if ln.startswith(("FAILED ", "ERROR "))]
    if rc not in (0, 1, 5, None) and not failures:  # crashed: collection error, abort, signal
        failures = [f"CRASHED {path} (exit {rc}): " + " | ".join(out.strip().splitlines()[-3:])]
        counts["errors"] += 1
    return {
        "file": path,
        "seconds": round(time.perf_counter() - t0, 1),
        "timed_out": rc is None,
        "exit": rc,
        **counts,
        "failures": failures,
        "log": out,
    }


def report(r: dict) -> None:
    flag = "TIMEOUT" if r["timed_out"] else ("ok" if not r["failures"] else "FAIL")
    print(
        f"  {r['file']:<40} {r['passed']:4d} passed {r['failed']:3d} failed "
        f"{r['seconds']:7.1f} s  {flag}",
        flush=True,
    )
    for line in r["failures"]:
        print(f"      {line[:220]}", flush=True)


def longest_first(files: list[str], previous: Path) -> list[str]:
    """Slow files first, so that none starts last and holds the run: by the seconds a
    previous run's JSON recorded, else by the file's size."""
    seconds: dict[str, float] = {}
    try:
        for row in json.loads(previous.read_text()):
            for f in row.get("files", []):
                seconds[f["file"]] = max(seconds.get(f["file"], 0.0), f["seconds"])
    except (OSError, ValueError, TypeError, KeyError):
        pass
    return sorted(files, key=lambda f: -seconds.get(f, (ROOT / f).stat().st_size / 100.0))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="*", help="test files (default: tests/test_*.py)")
    ap.add_argument("--devices", nargs="*", help="P:D selectors (default: every device)")
    ap.add_argument("--jobs", type=int, default=max(1, host_cores() // 2))
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per test file")
    ap.add_argument(
        "--budget", type=float, default=0.0, help="seconds for each device's whole run (0: none)"
    )
    ap.add_argument("--json", default="bench_results/suite_on_devices.json")
    ap.add_argument("--logs", help="folder for each file's pytest output")
    args = ap.parse_args()

    infos = {i.selector: i for i in list_devices()}
    if not infos:
        print("No OpenCL device found.", file=sys.stderr)
        return 2
    chosen = args.devices or list(infos)
    unknown = [s for s in chosen if s not in infos]
    if unknown:
        listing = "\n".join(f"  {s}  {i.platform} / {i.name}" for s, i in infos.items())
        print(f"Unknown device {', '.join(unknown)}. Devices:\n{listing}", file=sys.stderr)
        return 2
    files = args.files or sorted(str(p.relative_to(ROOT)) for p in ROOT.glob("tests/test_*.py"))
    files = longest_first(files, Path(args.json))

    rows = []
    for sel in chosen:
        info = infos[sel]
        print(
            f"{sel}  {info.platform} / {info.name} (driver {info.driver_version}): "
            f"{len(files)} files, {args.jobs} at a time",
            flush=True,
        )
        t0 = time.perf_counter()
        deadline = t0 + args.budget if args.budget > 0 else float("inf")
        logs = Path(args.logs) / sel.replace(":", "_") if args.logs else None
        if logs:
            logs.mkdir(parents=True, exist_ok=True)
        results = []
        with ThreadPoolExecutor(args.jobs) as pool:
            jobs = [pool.submit(run_file, f, sel, args.timeout, deadline) for f in files]
            for job in as_completed(jobs):  # each file reported as it ends
                r = job.result()
                results.append(r)
                report(r)
                if logs:
                    (logs / (Path(r["file"]).stem + ".log")).write_text(r["log"])
        results.sort(key=lambda r: r["file"])
        total = {k: sum(r[k] for r in results) for k in ("passed", "failed", "errors", "skipped")}
        rows.append(
            {
                "device": sel,
                "platform": info.platform,
                "name": info.name,
                "driver": info.driver_version,
                **total,
                "timed_out_files": [r["file"] for r in results if r["timed_out"]],
                "wall_s": round(time.perf_counter() - t0, 1),
                "files": [{k: v for k, v in r.items() if k != "log"} for r in results],
            }
        )

    print(
        f"\n{'device':<6} {'name':<34} {'driver':<16} {'passed':>6} {'failed':>6} "
        f"{'errors':>6} {'skipped':>7} {'timeouts':>8} {'wall s':>7}  verdict"
    )
    for row in rows:
        ok = not (row["failed"] or row["errors"] or row["timed_out_files"])
        print(
            f"{row['device']:<6} {row['name'][:34]:<34} {row['driver'][:16]:<16} "
            f"{row['passed']:6d} {row['failed']:6d} {row['errors']:6d} {row['skipped']:7d} "
            f"{len(row['timed_out_files']):8d} {row['wall_s']:7.0f}  {'PASS' if ok else 'FAIL'}"
        )
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1))
    return 0 if all(not (r["failed"] or r["errors"] or r["timed_out_files"]) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
