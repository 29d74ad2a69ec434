"""`clrefract bench`: the speed/accuracy table, its columns, and errors that fall as the
step shrinks (the smallest study: one scene, rkn4, float64)."""

import json

from clrefract.cli import main
from clrefract.tradeoff import COLUMNS


def test_bench_quick_table_falls_with_the_step(tmp_path, capsys):
    out = tmp_path / "bench"
    args = ["bench", "--quick", "--scenes", "voxel", "--precision", "float64"]
    args += ["--integrators", "rkn4", "--rays", "64", "--image", "16", "--out", str(out)]
    assert main(args) == 0
    table = (out / "tradeoff.md").read_text()
    assert table == capsys.readouterr().out
    head = [c.strip() for c in table.splitlines()[0].strip("|").split("|")]
    assert head == list(COLUMNS)
    for col in ("exit err max", "PSNR dB", "grad err", "device KiB", "ray-steps/s"):
        assert col in head
    assert (out / "tradeoff.png").stat().st_size > 10_000
    rows = sorted(json.loads((out / "tradeoff.json").read_text()), key=lambda r: -r["step"])
    assert [r["step"] for r in rows] == [2.0, 1.0, 0.5, 0.25]
    err = [r["error_max"] for r in rows]
    psnr = [r["psnr_db"] for r in rows]
    grad = [r["grad_error"] for r in rows]
    # fourth order: each halving cuts the exit error by about 16 (measured 14 to 12)
    assert all(b < a / 4 for a, b in zip(err, err[1:])), err
    assert all(b > a + 5 for a, b in zip(psnr, psnr[1:])), psnr
    # the adjoint against float64 differences at 1/16 mm: 2e-5 at 2 mm, then a floor of
    # about 1e-7 (64 rays: 8e-7, 8e-8, 1.3e-7; 512 rays: 1e-6, 3e-7, 2e-8)
    assert grad[-1] < grad[0] / 100 and max(grad) == grad[0], grad
    assert all(r["device_bytes"] > 64 * 6 * 8 for r in rows)  # at least the rays' inputs
    assert all(r["ray_steps_per_s"] > 0 for r in rows)


def test_bench_refuses_bad_sizes(tmp_path, capsys):
    assert main(["bench", "--quick", "--rays", "0", "--out", str(tmp_path / "b")]) == 2
    assert "--rays must be between 1" in capsys.readouterr().err
