"""`clrefract bench`: the speed/accuracy table, its columns, and errors that fall as the
step shrinks (the smallest study: one scene, rkn4, float64)."""

import json

import numpy as np
import pytest

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
    # the throughput columns are the rays and their steps over the best time
    for r in rows:
        per_s = 64 / r["seconds"]
        assert r["rays_per_s"] == pytest.approx(per_s, rel=1e-12)
        assert r["ray_steps_per_s"] == pytest.approx(per_s * r["steps_per_ray"], rel=1e-12)
    # and the steps those counted: the whole steps of sigma (arc length / eta) that fit along
    # each ray's straight path through the box (the blob, eta 1.063 at most, bends it little);
    # measured 0.0, 0.016, 0.078 and 0.14 steps off at steps 2 to 0.25 mm
    sigma = _sigma_lengths()
    for r in rows:
        want = np.floor(sigma / r["step"]).mean()
        assert abs(r["steps_per_ray"] - want) < 0.5, (r["step"], r["steps_per_ray"], want)


def _sigma_lengths(rays=64):
    """The integral of ds / eta (float64 NumPy field, trapezoids of 0.015 mm) along each
    of the study's rays (parallel to x) straight across the voxel scene's tracing box."""
    from clrefract.fields.base import Box
    from clrefract.tradeoff import SCENES, bundle

    field = SCENES["voxel"]()
    box = field.tracing_box(Box())
    o, _ = bundle(rays)
    x = np.linspace(box.lo[0], box.hi[0], 4001)
    pts = np.stack([np.column_stack([x, np.full_like(x, y), np.full_like(x, z)]) for _, y, z in o])
    eta = field.eval(pts.reshape(-1, 3))[0].reshape(rays, -1)
    return np.trapezoid(1 / eta, x, axis=1)


def test_bench_refuses_bad_sizes(tmp_path, capsys):
    assert main(["bench", "--quick", "--rays", "0", "--out", str(tmp_path / "b")]) == 2
    assert "--rays must be between 1" in capsys.readouterr().err
