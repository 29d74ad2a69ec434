"""tools/suite_on_devices.py: per-device pass / fail counts, failures named, a stalling file
stopped at its time limit, and an exit status that says whether everything passed."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_table_counts_passes_failures_and_timeouts(tmp_path):
    (tmp_path / "test_ok.py").write_text("def test_a():\n    assert 1 + 1 == 2\n")
    (tmp_path / "test_bad.py").write_text(
        "def test_b():\n    assert 1 + 1 == 2\n\ndef test_c():\n    assert 1 + 1 == 3\n"
    )
    (tmp_path / "test_slow.py").write_text("import time\n\ndef test_d():\n    time.sleep(60)\n")
    out = tmp_path / "suite.json"
    files = [str(tmp_path / f"test_{n}.py") for n in ("ok", "bad", "slow")]
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "tools" / "suite_on_devices.py"),
            "--devices",
            "0:0",
            "--jobs",
            "3",
            "--timeout",
            "8",
            "--json",
            str(out),
            *files,
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1, done.stdout + done.stderr
    (row,) = json.loads(out.read_text())
    assert (row["passed"], row["failed"], row["device"]) == (2, 1, "0:0")
    assert row["timed_out_files"] == [files[2]]
    bad = next(f for f in row["files"] if f["file"] == files[1])
    assert any("test_c" in line for line in bad["failures"])
    assert "FAIL" in done.stdout and "test_c" in done.stdout


def test_an_unknown_device_is_refused_with_the_list():
    done = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "suite_on_devices.py"), "--devices", "9:9"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert "Unknown device 9:9" in done.stderr and "0:0" in done.stderr
