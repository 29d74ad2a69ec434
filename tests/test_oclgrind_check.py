"""tools/oclgrind_check.py: a kernel that reads past its buffer and an uninitialised value
(with --uninitialised), and one whose work-items race, are each found at their kind, kernel
and line; a sound kernel passes with nothing found."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
from oclgrind_check import icd_library  # noqa: E402

# an environment condition, not a missing feature: tools/setup.sh installs oclgrind where apt
# works (CI's pip-only pass runs before it does)
pytestmark = pytest.mark.skipif(
    icd_library(None) is None, reason="oclgrind is not installed (tools/setup.sh installs it)"
)

KERNELS = '''
import numpy as np
import pyopencl as cl

SRC = """
__kernel void past_end(__global const float *a, __global float *out, int n) {
    int i = get_global_id(0);
    float t[4];
    if (i < 2) t[0] = 1.0f;
    out[i] = a[i + n] + t[0];
}
__kernel void racing(__global float *out) {
    out[0] = (float)get_global_id(0);
}
__kernel void sound(__global const float *a, __global float *out) {
    int i = get_global_id(0);
    out[i] = 2.0f * a[i];
}
"""


def run(name, *args):
    ctx = cl.create_some_context(interactive=False)
    q = cl.CommandQueue(ctx)
    flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
    a = cl.Buffer(ctx, flags, hostbuf=np.ones(8, np.float32))
    out = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 32)
    prg = cl.Program(ctx, SRC).build()
    getattr(prg, name)(q, (8,), (8,), *([a, out] if name != "racing" else [out]), *args)
    q.finish()
'''


def check(tmp_path, body: str, *flags: str):
    (tmp_path / "test_kernels.py").write_text(KERNELS + body)
    out = tmp_path / "check.json"
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "tools" / "oclgrind_check.py"),
            "--timeout",
            "120",
            "--json",
            str(out),
            *flags,
            str(tmp_path / "test_kernels.py"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    return done, json.loads(out.read_text())[0]


def test_reads_past_the_end_uninitialised_values_and_races_are_found(tmp_path):
    body = (
        "\n\ndef test_past_end():\n    run('past_end', np.int32(4))\n"
        "\n\ndef test_racing():\n    run('racing')\n"
    )
    done, row = check(tmp_path, body, "--uninitialised")
    assert done.returncode == 1, done.stdout + done.stderr
    assert row["passed"] == 2 and row["failed"] == 0  # the driver lets all of it pass
    found = {(d["kind"], d["kernel"], d["where"]) for d in row["kernel_diagnostics"]}
    line = "line 6: out[i] = a[i + n] + t[0];"
    assert ("invalid read", "past_end", line) in found
    assert ("uninitialised", "past_end", line) in found
    assert ("data race", "racing", "line 9: out[0] = (float)get_global_id(0);") in found
    # work-items 4..7 read past the 8 values, and write what they did not initialise
    counts = {(d["kind"], d["kernel"]): d["count"] for d in row["kernel_diagnostics"]}
    assert counts[("invalid read", "past_end")] == 4
    assert counts[("uninitialised", "past_end")] == 4
    assert "3 distinct kernel diagnostics (benign ones aside)" in done.stdout
    # without --uninitialised the same run reports the read past the end and the race alone
    done, row = check(tmp_path, body)
    assert done.returncode == 1
    assert {d["kind"] for d in row["kernel_diagnostics"]} == {"invalid read", "data race"}


def test_a_sound_kernel_passes_with_nothing_found(tmp_path):
    done, row = check(tmp_path, "\n\ndef test_sound():\n    run('sound')\n")
    assert done.returncode == 0, done.stdout + done.stderr
    assert row["passed"] == 1 and row["kernel_diagnostics"] == []
