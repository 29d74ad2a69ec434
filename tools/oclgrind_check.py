"""The kernel tests on Oclgrind's simulated device, which reports what a CPU driver lets pass
and a GPU compiler may not: reads and writes out of bounds, data races between work-items,
barriers not reached by a whole work-group, misuse of the OpenCL API, and with
--uninitialised, reads of uninitialised memory.

Each target (a test file, with pytest arguments) runs in its own pytest process on
Oclgrind (installed as an ICD of its own in a temporary folder: no other driver is seen), its
output kept whole (`-s`, where Oclgrind writes), and every diagnostic is counted by kind,
kernel and source line. Oclgrind interprets every work-item, so only the small kernel tests
are run, and slowly (minutes a file).

    python tools/oclgrind_check.py [--timeout 900] [--uninitialised] [--logs DIR]
                                   [--json bench_results/oclgrind_check.json]
                                   ["tests/test_x.py -k expr" ...]

Exit status 0 only when every target passed and no kernel diagnostic was found.
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import shutil
import sys
import tempfile
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from suite_on_devices import run_file  # noqa: E402

# the kernel-level tests of the fits' OpenCL sources, at sizes Oclgrind gets through, at one
# lane (Oclgrind presents itself as a GPU, whose layout that is). Oclgrind 21.10 computes some
# vector code wrong (clamp, min and max of an int vector against scalar bounds; `a && !b` on
# vectors gives 1 where OpenCL C says -1), so tests that ask for more lanes fail there for
# no fault of theirs; it crashes on the exact-Snell renderers (snell.cl, snell_sdf.cl),
# which are left out
TARGETS = (
    "tests/test_field_hashgrid.py -k kernel",
    "tests/test_adjoint_hashgrid.py -k kernel_adjoint_terms",
    "tests/test_hashgrid_distil.py -k 'device_passes_match and (1-eight-levels or 1-ramp)'",
    "tests/test_field_voxel.py -k 'kernel_matches_numpy_reference and (float64-1- or float32-1-)'",
    "tests/test_fields_analytic.py -k kernel",
    "tests/test_levelset.py -k 'kernel_matches and float64-1-'",
    "tests/test_tracer_oracles.py -k 'status_missed or parabolic_fibre'",
    "tests/test_adam.py -k device",
    "tests/test_baseline_neural.py -k device_field",
    "tests/test_skip_empty.py -k same_rays_with_fewer_steps",
    "tests/test_interface.py -k "
    "'sphere_crossings or right_angle or (gradient_matches and sphere-grid)'",
    "tests/test_interior.py -k 'sphere and (curved_crossings or gradient_matches)'",
)
ENV = {
    "CLREFRACT_NO_PIP_DRIVERS": "1",  # Oclgrind alone, not the pip drivers beside it
    "PYOPENCL_NO_CACHE": "1",  # a binary cached by another driver's build is no test
    "OCLGRIND_DATA_RACES": "1",
    "OCLGRIND_CHECK_API": "1",
    # past its default of 1,000 reports Oclgrind stays silent: a fault after many benign
    # races would go unseen
    "OCLGRIND_MAX_ERRORS": "1000000",
    # Oclgrind 21.10's interpreter lacks the intrinsic that restrict-qualified pointers
    # become once inlined (llvm.experimental.noalias.scope.decl): it cannot load the kernel
    "OCLGRIND_BUILD_OPTIONS": "-Drestrict=",
}
# the first line of each kind of diagnostic Oclgrind writes
KERNEL_KINDS = (
    ("invalid read", re.compile(r"^Invalid read of size")),
    ("invalid write", re.compile(r"^Invalid write of size")),
    ("uninitialised", re.compile(r"uninitiali[sz]ed value", re.I)),
    ("data race", re.compile(r"data race at", re.I)),
    ("divergence", re.compile(r"^Work-group divergence")),
    ("fatal", re.compile(r"^OCLGRIND FATAL ERROR")),
    ("other", re.compile(r"^(Invalid|Unaligned|Atomic|Barrier)\b")),
)
API_HEADER = "Oclgrind - OpenCL runtime error detected"
# diagnostics that are no fault, by kind and the code of one of their accesses, with why
BENIGN = (
    (
        "data race",
        re.compile(r"^old\.f = \*p;"),
        "atomic_add_real's compare-and-swap loop (OpenCL 1.2, no float atomics): its first "
        "guess is a plain read, and a stale or torn guess fails the swap, which returns the "
        "value to try next",
    ),
)


def icd_library(explicit: str | None) -> Path | None:
    """Oclgrind's ICD library: `explicit`, else the one beside the oclgrind command."""
    if explicit:
        return Path(explicit) if Path(explicit).is_file() else None
    exe = shutil.which("oclgrind")
    cands = [Path("/usr/lib/oclgrind/liboclgrind-rt-icd.so")]
    if exe:
        prefix = Path(exe).resolve().parent.parent
        cands = [prefix / "lib" / "oclgrind" / "liboclgrind-rt-icd.so", *cands]
    return next((c for c in cands if c.is_file()), None)


def diagnostics(log: str) -> tuple[Counter, Counter]:
    """Oclgrind's kernel diagnostics in a log, counted by (kind, kernel, source line, why it
    is benign or ""), and its API errors by (function, error)."""
    kernel: Counter = Counter()
    api: Counter = Counter()
    lines = log.splitlines()
    for i, line in enumerate(lines):
        text = line.strip()
        if text == API_HEADER:
            block = [s.strip() for s in lines[i + 1 : i + 4]]
            fn = next((s.split(":", 1)[1].strip() for s in block if s.startswith("Function:")), "?")
            err = next((s.split(":", 1)[1].strip() for s in block if s.startswith("Error:")), "?")
            api[(fn, err)] += 1
            continue
        kind = next((k for k, rx in KERNEL_KINDS if rx.search(text)), None)
        if kind is None:
            continue
        # a block runs to the first empty line (its inner separators hold a tab); the line
        # numbers are the built program's (sources and defines joined), so its code is kept.
        # A race names two accesses: the first is its line, either may make it benign
        name, places = "?", []
        block = lines[i + 1 : i + 20]
        for j, follow in enumerate(block):
            if not follow:
                break
            f = follow.strip()
            if f.startswith("Kernel:"):
                name = f.split(":", 1)[1].strip()
            elif f.startswith("At line"):
                at = re.match(r"At line (\d+)", f)
                code = block[j + 1].strip() if j + 1 < len(block) else ""
                places.append((at.group(1) if at else "?", code))
        where = f"line {places[0][0]}: {places[0][1]}" if places else "?"
        why = next(
            (r for k, rx, r in BENIGN if k == kind and any(rx.search(c) for _, c in places)), ""
        )
        kernel[(kind, name, where, why)] += 1
    return kernel, api


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("targets", nargs="*", help="test files with pytest arguments, each quoted")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per target")
    ap.add_argument("--icd", help="Oclgrind's liboclgrind-rt-icd.so (default: found)")
    ap.add_argument(
        "--uninitialised",
        action="store_true",
        help="report reads of uninitialised memory too (Oclgrind 21.10 takes a buffer zeroed "
        "by clEnqueueFillBuffer, as the fits' gradients and Adam moments are, for "
        "uninitialised)",
    )
    ap.add_argument("--json", default="bench_results/oclgrind_check.json")
    ap.add_argument("--logs", help="folder for each target's output")
    args = ap.parse_args()

    lib = icd_library(args.icd)
    if lib is None:
        print(
            "Oclgrind's ICD library (liboclgrind-rt-icd.so) was not found: install oclgrind "
            "(Debian: apt install oclgrind) or give --icd",
            file=sys.stderr,
        )
        return 2
    targets = args.targets or list(TARGETS)
    logs = Path(args.logs) if args.logs else None
    if logs:
        logs.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as vendors:
        (Path(vendors) / "oclgrind.icd").write_text(f"{lib}\n")
        env = dict(ENV, OCL_ICD_VENDORS=vendors)
        if args.uninitialised:
            env["OCLGRIND_UNINITIALIZED"] = "1"
        print(f"Oclgrind ({lib}): {len(targets)} targets, one at a time", flush=True)
        for target in targets:
            path, *extra = shlex.split(target)
            r = run_file(path, "0:0", args.timeout, float("inf"), ["-s", *extra], env)
            kernel, api = diagnostics(r["log"])
            if logs:
                stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", target)
                (logs / f"{stem}.log").write_text(r["log"])
            row = {
                "target": target,
                "passed": r["passed"],
                "failed": r["failed"] + r["errors"],
                "timed_out": r["timed_out"],
                "seconds": r["seconds"],
                "kernel_diagnostics": [
                    {"kind": k, "kernel": n, "where": w, "count": c, "benign": b or None}
                    for (k, n, w, b), c in sorted(kernel.items())
                ],
                "api_errors": [
                    {"function": f, "error": e, "count": c} for (f, e), c in sorted(api.items())
                ],
                "failures": r["failures"],
            }
            rows.append(row)
            flag = "TIMEOUT" if r["timed_out"] else ("ok" if not row["failed"] else "FAIL")
            faults = sum(c for key, c in kernel.items() if not key[3])
            print(
                f"  {target:<44} {row['passed']:4d} passed {row['failed']:3d} failed "
                f"{faults:5d} kernel {sum(kernel.values()) - faults:5d} benign "
                f"{sum(api.values()):4d} API {row['seconds']:7.1f} s  {flag}",
                flush=True,
            )
            for d in row["kernel_diagnostics"]:
                why = f" benign: {d['benign']}" if d["benign"] else ""
                print(f"      {d['kind']}: {d['kernel']} {d['where']} (x{d['count']}){why}")
            for d in row["api_errors"]:
                print(f"      API: {d['function']} {d['error']} (x{d['count']})")
            for line in row["failures"]:
                print(f"      {line[:220]}")

    found = sum(not d["benign"] for r in rows for d in r["kernel_diagnostics"])
    bad = [r["target"] for r in rows if r["failed"] or r["timed_out"]]
    print(
        f"\n{len(rows)} targets, {sum(r['passed'] for r in rows)} tests passed, "
        f"{len(bad)} targets failed or timed out, "
        f"{found} distinct kernel diagnostics (benign ones aside)"
    )
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1))
    return 0 if not (found or bad) else 1


if __name__ == "__main__":
    sys.exit(main())
