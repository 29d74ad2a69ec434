"""Which lane widths a driver can build and run, found once per driver and cached on disk.

A driver's compiler may fail on a vector built-in at one width only, and some fail by aborting
the whole process (pip PoCL 3.0: "LLVM ERROR: Cannot select ... rsqrt" at 16 lanes on znver3),
so the probe runs in a child process. It builds kernels_cl/probe.cl, which calls every built-in
the kernels use, at each width from 1 up, checks the numbers against NumPy and reports each
width as it goes: an abort at 16 lanes still leaves the narrower widths known.

    python -m clrefract.probe PLATFORM DEVICE PRECISION   (prints one JSON line per width)
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ..locations import cache_dir, kernel_source

WIDTHS = (1, 2, 4, 8, 16)
PROBE_TIMEOUT_S = 180.0
SLOW_BUILD_S = 30.0  # a probe this small builds in well under a second on a healthy driver


def reference(a: np.ndarray) -> np.ndarray:
    """float64 NumPy value of probe_builtins for inputs a in [0.5, 2)."""
    s = np.clip(a - 0.5, 0, 1)
    r = np.sqrt(a) + 1 / np.sqrt(a) + np.exp(-a) + np.log1p(a) + np.sin(a) + np.cos(a)
    r += np.arccos(np.clip(a - 1, -1, 1)) + np.abs(1 - a) + np.floor(a * 3)
    r += a + 0.25 * a + np.minimum(a, 1) + np.maximum(a, 1.5)
    r += np.copysign(a, 1 - a) + np.sign(a - 1) + s**3 * (s * (6 * s - 15) + 10)
    r += (a > 1).astype(float)
    r += np.minimum(np.floor(a * 4), 5)
    return r


def _probe_inputs(n: int) -> np.ndarray:
    # away from the floor() steps, so float32 rounding cannot change an integer part
    a = np.linspace(0.5, 2.0, n, endpoint=False) + 0.37 / n
    steps = np.concatenate([np.arange(1, 8) / 4, np.arange(1, 6) / 3])
    near = np.min(np.abs(a[:, None] - steps[None, :]), axis=1) < 1e-3
    a[near] += 2e-3
    return a


def probe_width(runtime, lanes: int, precision: str) -> dict:
    """Build and run the probe at one width in this process; returns a result record."""
    from ..errors import BuildError

    t0 = time.perf_counter()
    try:
        prg = runtime.build(["common.h", "probe.cl"], {"LANES": lanes}, precision)
        k = prg.probe_builtins
    except BuildError as exc:
        return {"lanes": lanes, "ok": False, "why": exc.compiler_error}
    t_build = time.perf_counter() - t0
    cl = runtime.cl
    dtype = runtime.real_dtype(precision)
    n = 64 * lanes
    a = _probe_inputs(n).astype(dtype)
    mf = cl.mem_flags
    ctx, q = runtime.context, runtime.queue
    a_d = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
    out = np.zeros(n, dtype)
    out_d = cl.Buffer(ctx, mf.WRITE_ONLY, out.nbytes)
    flags = np.zeros(1, np.int32)
    flags_d = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=flags)
    k(q, (n // lanes,), None, a_d, out_d, flags_d)
    cl.enqueue_copy(q, out, out_d)
    cl.enqueue_copy(q, flags, flags_d)
    q.finish()
    want = reference(a.astype(np.float64))
    err = float(np.max(np.abs(out - want) / (1 + np.abs(want))))
    tol = 1e-4 if precision == "float32" else 1e-10
    groups = int(np.sum((a.reshape(-1, lanes) > 1).any(axis=1)))
    ok = err < tol and int(flags[0]) == groups and t_build < SLOW_BUILD_S
    why = ""
    if err >= tol:
        why = f"wrong results (error {err:.1e})"
    elif int(flags[0]) != groups:
        why = f"wrong mask reduction ({int(flags[0])} != {groups})"
    elif t_build >= SLOW_BUILD_S:
        why = f"build took {t_build:.0f} s"
    return {"lanes": lanes, "ok": ok, "build_s": round(t_build, 3), "error": err, "why": why}


@functools.lru_cache(maxsize=1)
def _source_digest() -> str:
    """The probe's own code: a new probe invalidates what the old one found."""
    src = b"".join(p.read_bytes() for p in sorted(Path(__file__).parent.glob("*.py")))
    src += kernel_source("probe.cl").encode() + kernel_source("common.h").encode()
    return hashlib.sha1(src).hexdigest()[:12]


def _key(info, precision: str) -> str:
    return "|".join(
        [
            info.platform,
            info.platform_version,
            info.name,
            info.driver_version,
            info.version,
            precision,
            _source_digest(),
        ]
    )


def _cache_file() -> Path:
    return cache_dir() / "lanes.json"


def _read_cache() -> dict:
    try:
        return json.loads(_cache_file().read_text())
    except (OSError, ValueError):
        return {}


def _write_cache(key: str, value: dict) -> None:
    data = _read_cache()
    data[key] = value
    path = _cache_file()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_text(json.dumps(data, indent=1, sort_keys=True))
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only home only costs a probe per process


_MEMO: dict[tuple[str, str], dict] = {}  # reports found by this process, per cache file


def lane_report(info, precision: str) -> dict:
    """{'widths': [...usable...], 'results': [...per width...], 'note': str}, cached on disk
    and in this process."""
    key = _key(info, precision)
    memo = (str(_cache_file()), key)
    if memo not in _MEMO:
        _MEMO[memo] = _read_cache().get(key) or _probe(info, precision, key)
    return _MEMO[memo]


def why_unusable(report: dict) -> str:
    """Why a device whose report has no width cannot run the kernels ('' when it can)."""
    if report["widths"]:
        return ""
    why = next((r.get("why") for r in report["results"] if r.get("why")), report.get("note"))
    if "unknown target CPU" in (why or ""):
        why += " (the driver's LLVM does not recognise this CPU)"
    return why or "no lane width builds"


def _probe(info, precision: str, key: str) -> dict:
    """Run the probe in a child process and write its report to the disk cache."""
    cmd = [
        sys.executable,
        "-m",
        "clrefract.probe",
        str(info.platform_index),
        str(info.device_index),
        precision,
    ]
    note, lines = "", []
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S)
        lines, tail = proc.stdout.splitlines(), proc.stderr.strip().splitlines()
        if proc.returncode != 0:
            last = next((s for s in reversed(tail) if "rror" in s.lower()), None)
            note = f"the probe process ended with code {proc.returncode}"
            if last:
                note += f" ({last.strip()[:160]})"
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        lines = out.splitlines()
        note = f"the probe did not finish in {PROBE_TIMEOUT_S:.0f} s"
    results = []
    for s in lines:
        try:
            results.append(json.loads(s))
        except ValueError:
            continue
    done = {r["lanes"] for r in results}
    for w in WIDTHS:
        if w not in done:
            results.append({"lanes": w, "ok": False, "why": note or "not reached"})
    widths = [r["lanes"] for r in results if r["ok"]]
    report = {"widths": widths, "results": results, "note": note}
    _write_cache(key, report)
    return report
