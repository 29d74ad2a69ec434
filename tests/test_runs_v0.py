"""Run folders written by clrefract 0.1.0 before the fit became a package (tests/data/runs_v0:
a voxel Adam run and a hash grid's line search, each interrupted; a finished level-set line
search) resume, lengthen and evaluate, to the figures that version gave them."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from clrefract.evaluate import evaluate_run
from clrefract.fit import extend_run, prepare_fit
from clrefract.synth import MakeOptions, make_dataset

RUNS = Path(__file__).parent / "data" / "runs_v0"


@pytest.fixture(scope="module")
def sphere16(tmp_path_factory):
    """The dataset those runs were fitted on (make_dataset is deterministic)."""
    data = tmp_path_factory.mktemp("v0") / "sphere16"
    make_dataset("sphere", data, MakeOptions(views=10, res=16, env_width=128, volume_res=16))
    return data


def _rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


# what 0.1.0 itself measured, resuming the same folders (Debian's PoCL, float32): the loss
# of each resumed step and the held-out loss, and the test PSNR of the finish
RESUMED = {
    "voxel_adam": ([(3, 0.0039413, 0.0117475), (4, 0.0061606, 0.0117590)], 22.799),
    "hashgrid_guided": ([(2, 0.0018682, 0.00059731)], 23.122),
}


@pytest.mark.parametrize("name", sorted(RESUMED))
def test_an_interrupted_run_of_the_earlier_version_resumes_to_its_figures(sphere16, tmp_path, name):
    run = tmp_path / name
    shutil.copytree(RUNS / name, run)
    result = prepare_fit(sphere16, run, None, resume=True).run()
    steps, psnr = RESUMED[name]
    rows = _rows(run)
    assert [r["iteration"] for r in rows] == [s[0] for s in steps]
    for row, (_, loss, val) in zip(rows, steps):
        assert row["loss"] == pytest.approx(loss, rel=1e-2)
        assert row["val_loss"] == pytest.approx(val, rel=1e-2)
    assert result["test_psnr"] == pytest.approx(psnr, abs=0.1)
    assert (run / "field.npz").is_file()


def test_a_finished_run_of_the_earlier_version_evaluates_and_takes_more_steps(sphere16, tmp_path):
    run = tmp_path / "levelset_ls"
    shutil.copytree(RUNS / "levelset_ls", run)
    before = json.loads((run / "results.json").read_text())
    scores = evaluate_run(run, sphere16, tmp_path / "eval", figures=False)
    assert scores["psnr"] == pytest.approx(before["test_psnr"], abs=0.05)
    assert scores["chamfer_mm"] == pytest.approx(before["chamfer_mm"], abs=0.05)
    extend_run(run, 2)
    result = prepare_fit(sphere16, run, None, resume=True).run()
    assert [r["iteration"] for r in _rows(run)] == [1, 2]
    assert result["iterations"] == 2
    assert result["test_psnr"] > before["test_psnr"] - 1.0  # a step more keeps the fit
