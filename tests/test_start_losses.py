"""An interrupted start keeps its search's losses, and the same command takes them up."""

import io
import json

import numpy as np
import pytest

from clrefract.errors import ClrefractError
from clrefract.start_losses import NAME, StartLosses, count, fingerprint


def test_losses_are_kept_for_their_own_fingerprint_only(tmp_path):
    log = StartLosses(tmp_path, "a")
    log.put("empty|1|0", 0.25)
    log.put("visual|0|1.5|0", float("nan"))
    log.close()
    with (tmp_path / NAME).open("a") as f:
        f.write('{"key": "visual|0|1.6')  # the write an interruption cut short
    again = StartLosses(tmp_path, "a")
    assert again.get("empty|1|0") == 0.25 and np.isnan(again.get("visual|0|1.5|0"))
    assert again.get("visual|0|1.6|0") is None and again.reused == 2
    again.close()
    other = StartLosses(tmp_path, "b")  # other settings or data: nothing carried over
    assert other.known == {} and count(tmp_path) == 0
    other.close()


def test_the_fingerprint_follows_the_settings_and_the_dataset_files(tmp_path):
    (tmp_path / "images").mkdir()
    image = tmp_path / "images" / "r_000.exr"
    image.write_bytes(b"0" * 16)
    first = fingerprint("res = 64", tmp_path)
    assert fingerprint("res = 64", tmp_path) == first
    assert fingerprint("res = 48", tmp_path) != first
    (tmp_path / "run").mkdir()  # a run folder inside the dataset's is not part of it
    (tmp_path / "run" / NAME).write_text("{}\n")
    assert fingerprint("res = 64", tmp_path, tmp_path / "run") == first
    image.write_bytes(b"1" * 17)  # a photograph replaced
    assert fingerprint("res = 64", tmp_path) != first


def test_an_interrupted_start_is_taken_up_where_it_stopped(tmp_path, monkeypatch):
    """A level-set start on a small sphere, interrupted after 40 of its losses: the run
    folder keeps them (and no run), --resume says what to do, and the same command traces
    only the rest and picks the start of an uninterrupted run, to the bit."""
    from clrefract.fit import load_config, prepare_fit
    from clrefract.fit.objective import Objective
    from clrefract.fit.starts import search_losses
    from clrefract.synth import MakeOptions, make_dataset

    data = tmp_path / "sphere"
    make_dataset("sphere", data, MakeOptions(views=8, res=16, env_width=128, volume_res=16))
    settings = dict(field="levelset", res=16, iterations=1, batch=256, tighten_hull=False)
    total = 1 + search_losses(8, [6], 3)
    prepare_fit(data, tmp_path / "whole", load_config(None, settings))
    whole = json.loads((tmp_path / "whole" / "init.json").read_text())

    forward, calls = Objective.loss, []

    def interrupted(self, tracer, idx):
        if len(calls) == 40:
            raise KeyboardInterrupt
        calls.append(1)
        return forward(self, tracer, idx)

    run = tmp_path / "run"
    monkeypatch.setattr(Objective, "loss", interrupted)
    log = io.StringIO()
    with pytest.raises(KeyboardInterrupt):
        prepare_fit(data, run, load_config(None, settings), stream=log)
    assert f"40 losses of its search kept in {run / NAME}" in log.getvalue()
    assert not (run / "config.toml").exists() and count(run) == 40
    with pytest.raises(ClrefractError, match="without --resume"):
        prepare_fit(data, run, load_config(None, settings), resume=True)

    calls.clear()
    monkeypatch.setattr(
        Objective, "loss", lambda self, tracer, idx: calls.append(1) or forward(self, tracer, idx)
    )
    log = io.StringIO()
    prepare_fit(data, run, load_config(None, settings), stream=log)
    # the search visits a few candidates twice, and traces each once
    assert len(calls) == count(tmp_path / "whole") - 40 and count(run) == count(tmp_path / "whole")
    assert count(run) <= total
    assert "40 losses taken up from an earlier start" in log.getvalue()
    again = json.loads((run / "init.json").read_text())
    assert {k: again[k] for k in ("eta", "offset_mm", "smoothing_mm", "loss")} == {
        k: whole[k] for k in ("eta", "offset_mm", "smoothing_mm", "loss")
    }


def test_coarse_grids_of_a_small_start_trace_the_same_share_of_its_rays(
    sphere_12x24, tmp_path, monkeypatch
):
    """The benchmark below on the 24 x 24 sphere's few hundred mask rays, COARSE_RAYS set to
    a quarter of its batch: each candidate of the coarse grids (the hull's 7 offsets x 8
    indices, three shells' 8 indices) is traced on the same first quarter of the rays, every
    other on all of them. So few rays may rank otherwise (see COARSE_RAYS), so the start
    picked is held only to score within 10% of the whole batch's pick on the whole batch."""
    from clrefract.fit import load_config, prepare_fit
    from clrefract.fit import starts as fit_start
    from clrefract.fit.objective import Objective

    settings = dict(
        field="levelset", res=16, width=2.0, iterations=1, batch=512, tighten_hull=False,
        test_views=1,
    )  # fmt: skip
    forward, rays, picks = Objective.loss, {}, {}
    for share in (1, fit_start.COARSE_SHARE):
        traced = rays.setdefault(share, [])
        monkeypatch.setattr(fit_start, "COARSE_SHARE", share)
        monkeypatch.setattr(fit_start, "COARSE_RAYS", 512 // fit_start.COARSE_SHARE)

        def counted(self, tracer, idx, t=traced):
            t.append(np.array(idx))
            return forward(self, tracer, idx)

        monkeypatch.setattr(Objective, "loss", counted)
        prepare_fit(sphere_12x24, tmp_path / f"run{share}", load_config(None, settings))
        init = json.loads((tmp_path / f"run{share}" / "init.json").read_text())
        picks[share] = init
    whole, part = rays[1], rays[fit_start.COARSE_SHARE]
    n = len(whole[0])  # the rays through the masks: fewer than 512 here
    assert 256 < n <= 512 and all(np.array_equal(w, whole[0]) for w in whole)
    coarse = [p for p in part if len(p) < n]
    assert len(coarse) == 7 * 8 + 3 * 8  # the line searches after them may differ
    assert all(np.array_equal(c, whole[0][:128]) for c in coarse)
    assert all(np.array_equal(p, whole[0]) for p in part if len(p) == n)
    assert sum(map(len, part)) < 0.8 * sum(map(len, whole))
    assert picks[4]["loss"] < 1.1 * picks[1]["loss"], picks


@pytest.mark.benchmark  # about 70 to 90 s; test_coarse_grids_of_a_small_start_trace_the_same...
def test_coarse_grids_rank_on_a_share_of_the_rays_and_pick_the_whole_batchs_start(
    tmp_path, monkeypatch
):
    """The level set's coarse grids (offset x index, shells) trace fewer rays per candidate
    (a quarter, but no fewer than COARSE_RAYS), the same rays for each; the start picked
    is the one the whole batch picks."""
    from clrefract.fit import load_config, prepare_fit
    from clrefract.fit import starts as fit_start
    from clrefract.fit.objective import Objective
    from clrefract.synth import MakeOptions, make_dataset

    assert fit_start.coarse_rays(8192) == 2048 and fit_start.coarse_rays(4096) == 2048
    assert fit_start.coarse_rays(1024) == 1024  # small batches: every ray
    data = tmp_path / "sphere"
    make_dataset("sphere", data, MakeOptions(views=16, res=40, env_width=256, volume_res=16))
    settings = dict(field="levelset", res=16, iterations=1, batch=4096, tighten_hull=False)
    forward, rays, picks = Objective.loss, {}, {}
    for share in (1, fit_start.COARSE_SHARE):
        traced = rays.setdefault(share, [])
        monkeypatch.setattr(fit_start, "COARSE_SHARE", share)
        monkeypatch.setattr(fit_start, "COARSE_RAYS", 4096 // fit_start.COARSE_SHARE)

        def counted(self, tracer, idx, t=traced):
            t.append(len(idx))
            return forward(self, tracer, idx)

        monkeypatch.setattr(Objective, "loss", counted)
        prepare_fit(data, tmp_path / f"run{share}", load_config(None, settings))
        init = json.loads((tmp_path / f"run{share}" / "init.json").read_text())
        picks[share] = {k: init[k] for k in ("eta", "offset_mm", "smoothing_mm", "loss")}
    whole, part = rays[1], rays[fit_start.COARSE_SHARE]
    n = whole[0]  # the rays through the masks: fewer than 4,096 here
    assert 2048 < n <= 4096 and set(whole) == {n} and set(part) == {n, 1024}
    # the hull's coarse grid (7 offsets x 8 indices) and three shells' 8 indices each
    assert part.count(1024) == 7 * 8 + 3 * 8
    assert sum(part) < 0.8 * sum(whole)
    assert picks[1] == picks[fit_start.COARSE_SHARE], picks
