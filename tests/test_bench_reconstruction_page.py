"""tools/bench_reconstruction.py --page: the Markdown page of a benchmark's records, each
scene's figures and its gap to the ceiling as the records hold them, and the command that
measures it again."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))

from bench_reconstruction import page  # noqa: E402


def _row(scene, empty, start, fit, ceiling, **extra):
    return {
        "scene": scene,
        "field": "auto",
        "model": "voxel",
        "empty": {"test_psnr": empty},
        "start": {"test_psnr": start},
        "fit": {"test_psnr": fit, "eta_rmse": 0.0123, "best_iteration": 575, "seconds": 431.4},
        "ceiling": None if ceiling is None else {"test_psnr": ceiling},
        **extra,
    }


def _args(**over):
    base = dict(suite="graded", field="auto", page="docs/graded.md", views=100, res=128)
    return SimpleNamespace(**{**base, "grid": 64, "ceiling_grids": [], **over})


def test_the_page_gives_each_scene_its_figures_and_its_gap_to_the_ceiling():
    args = _args()
    rows = [
        _row("luneburg", 22.45, 25.12, 26.674, 29.76, device="PoCL 6.0 (cpu)"),
        _row("blobs:1", 22.91, 23.28, 40.12, 38.25, device="PoCL 6.0 (cpu)"),
        _row("plume", 58.23, 58.23, 73.70, None),
    ]
    text = page(rows, args)
    lines = text.splitlines()
    assert (
        "python tools/bench_reconstruction.py --suite graded --field auto --page docs/graded.md"
        in lines
    )
    table = [ln for ln in lines if ln.startswith("| ") and "---" not in ln]
    assert table[1] == (
        "| luneburg | voxel | 22.45 | 25.12 | **26.67** | 29.76 | -3.09 | 0.012 | 575 | 431 |"
    )
    assert table[2].split(" | ")[5:7] == ["38.25", "+1.87"]
    assert table[3].split(" | ")[5:7] == ["-", "-"]  # no ceiling recorded
    assert "- Device: PoCL 6.0 (cpu); not recorded." in lines
    assert len(table) == 1 + len(rows)


def test_the_page_lists_the_truth_on_finer_grids_and_its_command_asks_for_them():
    args = _args(suite="paper", field="interface", page="p.md", ceiling_grids=[128, 192])
    finer = [{"grid": 128, "test_psnr": 27.871}, {"grid": 192, "test_psnr": 29.305}]
    rows = [
        _row("prism", 22.58, 23.05, 23.05, 25.72, ceilings=finer),
        _row("sphere", 22.0, 30.0, 36.0, 40.0, ceilings=[]),
    ]
    lines = page(rows, args).splitlines()
    assert (
        "python tools/bench_reconstruction.py --suite paper --field interface "
        "--ceiling-grids 128,192 --page p.md" in lines
    )
    assert "- prism 27.87 dB at 128^3, 29.30 dB at 192^3" in lines
    assert not [ln for ln in lines if ln.startswith("- sphere")]
