"""RUN/report.html: one self-contained page of a run, written by `clrefract report RUN` and at
the end of `clrefract fit`, that names every test view; run.json's record of where a run
came from."""

from __future__ import annotations

import base64
import json
import os
import shutil
from datetime import datetime
from pathlib import Path

import pytest

from clrefract.cli import main
from clrefract.synth import MakeOptions, make_dataset

RUNS = Path(__file__).parent / "data" / "runs_v0"
SECTIONS = ("Scores", "Loss", "Test views", "eta through the box centre", "Surface", "Settings")


@pytest.fixture(scope="module")
def sphere16(tmp_path_factory):
    """The dataset the runs of tests/data/runs_v0 were fitted on."""
    data = tmp_path_factory.mktemp("report") / "sphere16"
    make_dataset("sphere", data, MakeOptions(views=10, res=16, env_width=128, volume_res=16))
    return data


def _check_page(page: str, views: list[str]) -> None:
    assert views
    for name in views:
        assert f"<b>{name}</b>" in page, name
    for section in SECTIONS:
        assert f"<h2>{section}" in page, section
    # self-contained: every picture inlined (the loss, each view, the slices, the surface)
    assert page.count('src="data:image/png;base64,') >= len(views) + 3
    assert 'src="http' not in page and "<link" not in page


def test_report_of_a_finished_run_renders_its_test_views(sphere16, tmp_path, capsys):
    """A run of 0.1.0 keeps no test/ images: the page renders its test views from the
    field on the dataset, and shows its scores and settings."""
    run = tmp_path / "levelset_ls"
    shutil.copytree(RUNS / "levelset_ls", run)
    assert main(["report", str(run), "--dataset", str(sphere16)]) == 0
    assert "report.html" in capsys.readouterr().err
    page = (run / "report.html").read_text()
    results = json.loads((run / "results.json").read_text())
    _check_page(page, [v["view"] for v in results["views"]])
    assert f"{results['test_psnr']:.2f}" in page
    assert "optimizer" in page  # config.toml
    # without a dataset (the one run.json names is gone) the page still comes, and says why
    meta = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**meta, "dataset": str(tmp_path / "gone")}))
    assert main(["report", str(run), "--out", str(tmp_path / "bare.html")]) == 0
    bare = (tmp_path / "bare.html").read_text()
    assert "not shown" in bare and "pass --dataset" in bare


def test_fit_writes_the_report_and_records_where_the_run_came_from(sphere16, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["fit", str(sphere16), "--out", str(run), "--field-kind", "voxel", "--init", "empty"]
    args += ["--grid-res", "8", "--step", "4", "--iterations", "2", "--test-views", "1"]
    assert main(["--quiet", *args]) == 0
    captured = capsys.readouterr()
    assert "start:" not in captured.err and "it/s" not in captured.err  # --quiet
    assert "test_psnr" in json.loads(captured.out)
    results = json.loads((run / "results.json").read_text())
    page = (run / "report.html").read_text()
    _check_page(page, [v["view"] for v in results["views"]])
    # the page inlines the loss figure the fit's finish drew, unless metrics came after it
    drawn = base64.b64encode((run / "loss.png").read_bytes()).decode()
    assert drawn in page
    os.utime(run / "metrics.jsonl")
    assert main(["report", str(run), "--out", str(tmp_path / "later.html")]) == 0
    assert drawn not in (tmp_path / "later.html").read_text()
    meta = json.loads((run / "run.json").read_text())
    assert {"dataset", "box", "eta_max"} <= set(meta)  # the keys a run had before
    assert meta["command"].startswith("clrefract --quiet fit ")
    assert meta["version"] and meta["device"] and meta["driver"]
    assert meta["commit"] is None or len(meta["commit"]) == 40
    started = datetime.fromisoformat(meta["started"])
    assert started.utcoffset().total_seconds() == 0
    assert datetime.fromisoformat(meta["ended"]) >= started
    assert "resumed" not in meta
    # a resumed run keeps its start and records the resuming command
    assert main(["fit", str(sphere16), "--out", str(run), "--resume", "--iterations", "2"]) == 0
    again = json.loads((run / "run.json").read_text())
    assert again["started"] == meta["started"] and again["command"] == meta["command"]
    assert again["resumed"][0]["command"].endswith("--resume --iterations 2")
