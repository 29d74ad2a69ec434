"""The level set's line-search optimiser (clrefract/fit/linesearch.py, optimizers.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from clrefract.errors import ClrefractError
from clrefract.fit import LINE_SEARCH_ITERATIONS, load_config


@pytest.mark.parametrize(
    "overrides, message",
    [
        (dict(field="hashgrid", init="empty"), "surface from the visual hull"),
        (dict(field="voxel"), "field 'voxel' uses optimizer 'adam'"),
        (dict(line_batch=-1), "line_batch must be >= 0"),
        (dict(refit_iterations=0), "refit_iterations must be at least 1"),
        (dict(keep_growth=1.0), "keep_growth must be above 1"),
        (dict(grad_sigma=-1.0), "grad_sigma must be one or more scales >= 0"),
        (dict(grad_sigma=(3.0, "x")), "grad_sigma must be one or more scales >= 0"),
        (dict(grad_sigma=()), "grad_sigma must be one or more scales >= 0"),
        (dict(line_steps=()), "line_steps must be positive"),
        (dict(line_steps=("a",)), "line_steps must be positive"),
        (dict(line_steps=(0.01, -0.1)), "line_steps must be positive"),
        (dict(env_blur=2.0), "compares sharp pixels"),
        (dict(block=8), "compares sharp pixels"),
        (dict(optimizer="sgd"), "optimizer must be one of adam, line-search, descent"),
    ],
)
def test_line_search_config_is_refused_where_it_cannot_work(overrides, message):
    base = dict(field="levelset", optimizer="line-search")
    with pytest.raises(ClrefractError, match=message):
        load_config(None, {**base, **overrides})


def test_a_line_search_takes_its_own_number_of_steps_unless_told(tmp_path):
    line = dict(field="levelset", optimizer="line-search")
    assert load_config(None, line).iterations == LINE_SEARCH_ITERATIONS < 100
    assert load_config(None, {**line, "iterations": 3}).iterations == 3
    toml = tmp_path / "fit.toml"
    toml.write_text('field = "levelset"\noptimizer = "line-search"\niterations = 5\n')
    assert load_config(toml, {}).iterations == 5
    toml.write_text('field = "levelset"\noptimizer = "line-search"\n')
    assert load_config(toml, {}).iterations == LINE_SEARCH_ITERATIONS
    assert load_config(None, {}).iterations == 600  # Adam's


def test_smoothing_keeps_the_gradients_sum_and_spreads_a_spike():
    from clrefract.fit.linesearch import smoothed

    g = np.zeros((32, 32, 32))
    g[16, 16, 16] = 1.0
    s = smoothed(g.ravel(), g.shape, 2.0).reshape(g.shape)
    assert s.sum() == pytest.approx(1.0, rel=1e-9)  # away from the edges
    # the peak (2 pi sigma^2)^-1.5 = 0.00794; two sigmas away exp(-2) of it
    assert s[16, 16, 16] == pytest.approx(0.00794, rel=0.02)
    assert s[16, 16, 20] == pytest.approx(np.exp(-2) * s[16, 16, 16], rel=0.02)
    assert np.array_equal(smoothed(g.ravel(), g.shape, 0.0), g.ravel())


def test_several_scales_weigh_broad_errors_by_their_size(tmp_path):
    """grad_sigma's scales sum their smoothings weighted by sigma^2: a gradient that is the
    same everywhere (a uniform growth of the surface) comes out sum(sigma^2) times itself,
    a spike about once (each Gaussian's peak times sigma^2 falls as 1 / sigma): broad errors
    move faster than ripples. A single number, as the config files of earlier runs hold,
    is one scale."""
    from clrefract.fit.linesearch import smoothed

    shape = (32, 32, 32)
    flat = np.ones(int(np.prod(shape)))
    scales = (3.0, 6.0, 12.0)
    assert np.allclose(smoothed(flat, shape, scales), 9 + 36 + 144)
    spike = np.zeros(shape)
    spike[16, 16, 16] = 1.0
    peak = smoothed(spike.ravel(), shape, scales).reshape(shape)[16, 16, 16]
    expected = sum(s * s * (2 * np.pi * s * s) ** -1.5 for s in scales)
    assert peak == pytest.approx(expected, rel=0.03)
    assert peak < 0.01 * (9 + 36 + 144)
    line = dict(field="levelset", optimizer="line-search")
    assert load_config(None, line).grad_sigma == scales
    toml = tmp_path / "config.toml"
    toml.write_text('field = "levelset"\noptimizer = "line-search"\ngrad_sigma = 3.0\n')
    assert load_config(toml, {}).grad_sigma == (3.0,)
    toml.write_text('field = "levelset"\noptimizer = "line-search"\ngrad_sigma = [2, 4]\n')
    assert load_config(toml, {}).grad_sigma == (2.0, 4.0)


def _sphere_run(data, tmp_path, **overrides):
    """A fit on the sphere dataset `data` (sphere_25x48: 48 x 48 pixels, 25 views), validated
    every step on 4 held-out views (sphere_12x24: 1): its results, the start's held-out loss,
    its metrics rows, and the Fit."""
    from clrefract.fit import prepare_fit

    cfg = load_config(None, dict(validate_every=1, val_views=4, **overrides))
    fit = prepare_fit(data, tmp_path / "run", cfg)
    start = fit.validation_loss()
    result = fit.run()
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").open()]
    return result, start, rows, fit


@pytest.mark.benchmark  # about 80 s; test_two_line_search_steps_lower_the_held_out_loss
def test_line_search_lowers_the_held_out_loss_from_the_hull_start(sphere_25x48, tmp_path):
    """The held-out claim at the size of a test: a glass sphere at 48 x 48 pixels, the level
    set from its visual-hull start, four line-search steps lower the held-out views' loss
    under 0.9 of the start's (Debian's PoCL: 0.34; six steps: 0.18, the test views 34.30
    -> 38.67 dB; from a start of 8,192 rays, four runs that the backward pass's float atomics
    make differ, 0.55 to 0.83; Adam at its defaults 0.99). The test views are not asserted:
    on pip's PoCL, whose start differed (37.82 dB), they once lost 0.93 while the held-out
    loss passed."""
    result, start, rows, _ = _sphere_run(
        sphere_25x48,
        tmp_path,
        field="levelset",
        res=32,
        iterations=4,
        optimizer="line-search",
        tighten_hull=False,  # a sphere's hull is round, and not hollow: the start picks
        shell_starts=False,  # neither shape, and they would take 60% of its losses
        batch=4096,  # the start's rays (half its time); the steps' as by default:
        line_batch=8192,
    )
    assert len(rows) == 4 and all(0.5 < r["kept"] <= 1.0 for r in rows), rows
    assert result["best_val_loss"] < 0.9 * start, (result["best_val_loss"], start)


@pytest.mark.benchmark  # about 75 s each; test_a_small_hash_grid_follows_its_level_set_down
@pytest.mark.parametrize("refit", ["best", "step"])
def test_hash_grid_follows_its_level_set_down_and_resumes_with_it(sphere_25x48, tmp_path, refit):
    """The hash grid from a perturbed start (distilled from the level set searched on the
    hull of all views but a fifth, 0.4 mm larger than the sphere) moves the level set it came
    from by the line search: on a 48 x 48 sphere, three steps take the held-out loss under
    0.9 of the start's, the level set's and the grid's fitted to it alike. With refit =
    "best" the held-out views judge the level set and the grid is fitted to the best step
    once; with "step", after each move (with the distillation defaults, 8,192 start rays and
    six steps, Debian's PoCL: 0.52 of it, the test views 33.50 -> 35.04 dB).
    From the default hull, which leaves out views with holes and hugs the sphere, the start's
    held-out loss is 0.00054 and four steps reach 0.94 of it. A resumed run takes up the same
    level set from its checkpoint, and the grid's index where its guide's index moved."""
    from clrefract.fit import prepare_fit

    overrides = dict(
        hull_tolerance=0.2,
        hull_carve=0.0,
        field="hashgrid",
        width=1.0,
        res=32,
        iterations=3,
        optimizer="line-search",
        distil_iterations=300,
        refit_iterations=150 if refit == "step" else 50,  # the end's: 600 (FINAL_REFIT)
        refit=refit,
        tighten_hull=False,  # a sphere's visual hull is round already
        shell_starts=False,  # and not hollow
        batch=4096,  # the start's rays (half its time); the steps' are line_batch's
        test_views=2,
        index_steps=(0.01, 0.03),
        validate_every=1,
        val_views=4,
        size_search=False,  # its test is its own (below); here it would add a third
    )
    data = sphere_25x48
    fit = prepare_fit(data, tmp_path / "run", load_config(None, overrides))
    start, grid_start = (
        fit.validation_loss(),
        fit.held_out_loss(fit.optimizer.validation_tracer(fit)),
    )
    result = fit.run()
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").open()]
    moved = [r for r in rows if r["step_mm"] > 0]
    assert len(moved) >= 2, rows
    assert result["best_val_loss"] < 0.9 * start, (result["best_val_loss"], start)
    grid = fit.held_out_loss(fit.optimizer.validation_tracer(fit))
    assert grid < 0.9 * grid_start, (grid, grid_start)
    if refit == "step":
        assert all(r["distilled_rms"] < 0.01 for r in moved), rows
    else:
        assert not any("distilled_rms" in r for r in rows), rows
        assert result["final_refit"]["distilled_rms"] < 0.01, result["final_refit"]

    again = prepare_fit(data, fit.out, load_config(None, overrides), resume=True)
    assert again.it == 3
    assert np.array_equal(again.optimizer.guide.params, fit.optimizer.guide.params)
    # a run in progress renders what its steps move: the level set, unless the grid follows
    from clrefract.fields.hashgrid import HashGridField
    from clrefract.fit import field_from_run

    shown = field_from_run(fit.out)
    if refit == "best":
        assert np.array_equal(shown.data(), fit.optimizer.guide.params)
    else:
        assert isinstance(shown, HashGridField)
    # the grid's top index follows its guide's, through the checkpoint and the best kept
    top = again.field.config.eta_max
    guide_index = again.optimizer.guide.params[-1]
    assert top == pytest.approx(again.kind.eta_top(again.cfg, guide_index), abs=1e-12)
    kept = HashGridField.load(fit.out / "field.npz").config.eta_max
    assert kept == pytest.approx(fit.best.eta_max or top, abs=1e-12)
    idx = fit.rays.mask_batch((5,))
    rays = fit.rays.origins[idx], fit.rays.dirs[idx]
    with_guide = fit.optimizer.guide.tracer.trace(*rays)
    resumed = again.optimizer.guide.tracer.trace(*rays)
    assert np.allclose(resumed.direction, with_guide.direction, atol=1e-6)


def test_two_line_search_steps_lower_the_held_out_loss(sphere_12x24, tmp_path):
    """The benchmark above at the size of a quick test: a 16^3 level set with a 2 mm
    interface on the 24 x 24 sphere, from its visual-hull start. Each step finds a move that
    lowers its own rays' loss, and the best of two steps takes the held-out view's loss under
    0.8 of the start's (measured 0.57)."""
    result, start, rows, _ = _sphere_run(
        sphere_12x24,
        tmp_path,
        field="levelset",
        res=16,
        width=2.0,
        iterations=2,
        optimizer="line-search",
        tighten_hull=False,
        shell_starts=False,
        batch=512,
        test_views=1,
    )
    assert len(rows) == 2 and all(0.5 < r["kept"] <= 1.0 for r in rows), rows
    assert all(r["step_mm"] > 0 for r in rows), rows
    assert all(r["loss_kept_after"] < r["loss_kept"] for r in rows), rows
    assert result["best_val_loss"] < 0.8 * start, (result["best_val_loss"], start)


@pytest.mark.parametrize("refit", ["best", "step"])
def test_a_small_hash_grid_follows_its_level_set_down(sphere_12x24, tmp_path, refit):
    """The benchmark above on the 24 x 24 sphere: a small hash grid (4 levels of 2^12)
    distilled from a 16^3 level set with a 2 mm interface, two line-search steps. Both steps
    move the surface; the best held-out loss falls under 0.9 of the start's (measured 0.82
    with refit = "best", judging the level set; 0.61 to 0.74 with "step", the grid: the
    distillation's threads add in any order), and so does the grid's (0.40 to 0.74); the
    grid follows its guide to an RMS error of eta under 0.03 (measured 0.013 to 0.018). A
    resumed run takes up the same level set, its index and the grid's top index."""
    from clrefract.fields.hashgrid import HashGridField
    from clrefract.fit import field_from_run, prepare_fit

    overrides = dict(
        hull_tolerance=0.2,
        hull_carve=0.0,
        field="hashgrid",
        width=2.0,
        res=16,
        levels=4,
        log2_table=12,
        hidden=16,
        iterations=2,
        optimizer="line-search",
        distil_iterations=50,
        refit_iterations=20 if refit == "step" else 10,
        refit=refit,
        tighten_hull=False,
        shell_starts=False,
        batch=512,
        test_views=1,
        index_steps=(0.01, 0.03),
        validate_every=1,
        val_views=2,
        size_search=False,
    )
    data = sphere_12x24
    fit = prepare_fit(data, tmp_path / "run", load_config(None, overrides))
    start = fit.validation_loss()
    grid_start = fit.held_out_loss(fit.optimizer.validation_tracer(fit))
    result = fit.run()
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").open()]
    assert len(rows) == 2 and all(r["step_mm"] > 0 for r in rows), rows
    assert result["best_val_loss"] < 0.9 * start, (result["best_val_loss"], start)
    grid = fit.held_out_loss(fit.optimizer.validation_tracer(fit))
    assert grid < 0.9 * grid_start, (grid, grid_start)
    if refit == "step":
        assert all(r["distilled_rms"] < 0.03 for r in rows), rows
    else:
        assert not any("distilled_rms" in r for r in rows), rows
        assert result["final_refit"]["distilled_rms"] < 0.03, result["final_refit"]

    again = prepare_fit(data, fit.out, load_config(None, overrides), resume=True)
    assert again.it == 2
    assert np.array_equal(again.optimizer.guide.params, fit.optimizer.guide.params)
    shown = field_from_run(fit.out)
    if refit == "best":
        assert np.array_equal(shown.data(), fit.optimizer.guide.params)
    else:
        assert isinstance(shown, HashGridField)
    top = again.field.config.eta_max
    guide_index = again.optimizer.guide.params[-1]
    assert top == pytest.approx(again.kind.eta_top(again.cfg, guide_index), abs=1e-12)
    kept = HashGridField.load(fit.out / "field.npz").config.eta_max
    assert kept == pytest.approx(fit.best.eta_max or top, abs=1e-12)
    idx = fit.rays.mask_batch((5,))
    rays = fit.rays.origins[idx], fit.rays.dirs[idx]
    with_guide = fit.optimizer.guide.tracer.trace(*rays)
    resumed = again.optimizer.guide.tracer.trace(*rays)
    assert np.allclose(resumed.direction, with_guide.direction, atol=1e-6)


@pytest.fixture(scope="module")
def one_step_run(_sphere_8x24, tmp_path_factory):
    """A one-step line search of a 16^3 level set on the 24 x 24 sphere of 8 views
    (sphere_8x24), through the command line; tests resume copies of it (_one_step_run)."""
    from clrefract.cli import main

    root = tmp_path_factory.mktemp("one_step")
    toml = root / "fit.toml"
    toml.write_text("tighten_hull = false\nshell_starts = false\n")
    fit = ["fit", str(_sphere_8x24[0]), "--out", str(root / "run"), "--field", "levelset"]
    line = ["--optimizer", "line-search", "--batch", "1024", "--test-views", "1"]
    assert main([*fit, "--res", "16", *line, "--iterations", "1", "--config", str(toml)]) == 0
    return root / "run"


def _one_step_run(data, one_step_run, tmp_path):
    """A copy of one_step_run in tmp_path: `clrefract.cli.main`, the run folder, and the fit
    command's arguments (without --optimizer) that resume it."""
    import shutil

    from clrefract.cli import main

    run = tmp_path / "run"
    shutil.copytree(one_step_run, run)
    fit = ["fit", str(data), "--out", str(run), "--field", "levelset", "--res", "16"]
    return main, run, fit


def test_resume_adds_steps_to_a_finished_line_search(sphere_8x24, one_step_run, tmp_path, capsys):
    """`--resume --iterations N` lengthens a line-search run (its steps have no schedule
    that depends on their count); it cannot shorten one."""
    main, run, fit = _one_step_run(sphere_8x24, one_step_run, tmp_path)
    assert main([*fit, "--resume", "--iterations", "2"]) == 0
    rows = [json.loads(x) for x in (run / "metrics.jsonl").open()]
    assert [r["iteration"] for r in rows] == [1, 2]
    assert load_config(run / "config.toml", {}).iterations == 2
    capsys.readouterr()
    assert main([*fit, "--resume", "--iterations", "1"]) == 2
    assert "can only add steps" in capsys.readouterr().err
    assert load_config(run / "config.toml", {}).iterations == 2


@pytest.mark.parametrize("bad", [("a",), (0.01, 0.0), (float("inf"),)])
def test_index_steps_must_be_positive_moves(bad):
    with pytest.raises(ClrefractError, match="index_steps must be positive"):
        load_config(None, dict(field="levelset", optimizer="line-search", index_steps=bad))


@pytest.mark.benchmark  # about 85 s; test_two_line_search_steps_raise_a_low_index
def test_line_search_moves_a_wrong_index_towards_the_truth(sphere_25x48, tmp_path):
    """A level set on the 48 x 48 sphere (index 1.5) set to index 1.35 after its start: four
    steps that may move the index by 0.01 or 0.03 down its gradient take it at least 0.05
    nearer the truth (Debian's PoCL: 1.47 in four moves of 0.03, where the start searched
    1.495 on a hull 1.95 mm too big), and not past it."""
    from clrefract.fit import prepare_fit

    data = sphere_25x48
    cfg = load_config(
        None,
        dict(
            field="levelset",
            res=32,
            iterations=4,
            optimizer="line-search",
            index_steps=(0.01, 0.03),
            val_views=4,
            tighten_hull=False,
            shell_starts=False,
            batch=4096,  # the start's rays; the steps' as by default
            line_batch=8192,
        ),
    )
    fit = prepare_fit(data, tmp_path / "run", cfg)
    fit.params[-1] = 1.35
    fit.bound.set_params(fit.params, fit.it)
    fit.run()
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").open()]
    index = [r["index"] for r in rows]
    assert index[-1] > 1.40 and index[-1] < 1.53, index
    moves = [round(abs(r["index_move"]), 9) for r in rows]
    assert set(moves) <= {0.0, 0.01, 0.03} and moves[0] == 0.03, rows


def test_two_line_search_steps_raise_a_low_index(sphere_12x24, tmp_path):
    """The benchmark above on the 24 x 24 sphere (a 16^3 level set, 2 mm interface), its
    index set to 1.2 after its start (which searched 1.34 at these pixels): the first of two
    steps moves the index up by the larger of its steps, and the two raise it by at least
    0.04 (measured 1.26, two moves of 0.03), not past the truth."""
    from clrefract.fit import prepare_fit

    cfg = load_config(
        None,
        dict(
            field="levelset",
            res=16,
            width=2.0,
            iterations=2,
            optimizer="line-search",
            index_steps=(0.01, 0.03),
            val_views=2,
            tighten_hull=False,
            shell_starts=False,
            batch=512,
            test_views=1,
        ),
    )
    fit = prepare_fit(sphere_12x24, tmp_path / "run", cfg)
    assert fit.params[-1] > 1.25  # the start's own index, well above where it is set
    fit.params[-1] = 1.2
    fit.bound.set_params(fit.params, fit.it)
    fit.run()
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").open()]
    index = [r["index"] for r in rows]
    assert index[-1] >= 1.24 - 1e-9 and index[-1] < 1.53, index
    moves = [round(r["index_move"], 9) for r in rows]
    assert set(moves) <= {0.0, 0.01, 0.03} and moves[0] == 0.03, rows


def test_size_search_grows_a_shrunk_sphere_and_raises_its_index(sphere_25x48, tmp_path):
    """The true 48 x 48 sphere (index 1.5) on a level set's grid, shrunk by 0.2 mm at index
    1.45: the size and index search finds the valley where size and index trade off (at
    these pixels of 0.5 mm it is flat along a growth of 0.2 mm), so the index rises by at
    least 0.02, not past 1.53, the sphere does not shrink further, and the held-out loss it
    keeps is under 0.2 of the shrunk sphere's (Debian's PoCL: not grown, index 1.4815, 0.06
    of it)."""
    import io

    from clrefract.fields.levelset import LevelSetField
    from clrefract.fit import Fit
    from clrefract.fit.finishes import size_index_search
    from clrefract.report import scene_truth

    data = sphere_25x48
    cfg = load_config(
        None, dict(field="levelset", res=32, optimizer="line-search", val_views=4, batch=4096)
    )
    fit = Fit(data, tmp_path / "run", cfg, stream=io.StringIO())
    fit.bind(fit.make_field(fit.start_grid()))
    truth = scene_truth(fit.ds)
    shape = fit.field.phi.shape
    phi = LevelSetField.from_sdf(lambda p: truth.sdf(p)[0], fit.box, shape, 1.5, cfg.width)
    fit.bound.set_params(np.append(phi.data()[:-1] + 0.2, 1.45), fit.it)
    row = size_index_search(fit, fit.bound)
    assert row["kept"], row
    assert row["grow_mm"] >= 0.0 and 1.47 <= row["index"][1] <= 1.53, row
    before, after = row["held_out_loss"]
    assert after < 0.2 * before, row
    assert np.allclose(fit.params[:-1], phi.data()[:-1] + 0.2)  # the field it had, back
    assert np.allclose(fit.best.params[:-1], fit.params[:-1] - row["grow_mm"])


def test_resume_with_another_width_narrows_a_finished_line_search(
    sphere_8x24, one_step_run, tmp_path, capsys
):
    """`--resume --width W` records the new interface in config.toml and ends the run there:
    its best level set searched for size and index at W (results.json says what the search
    did), and judged against the earlier width's field on the held-out views; the earlier
    field stays where it scores better (a 4 mm ramp blurs the 0.5 mm sphere), with its
    width."""
    main, run, fit = _one_step_run(sphere_8x24, one_step_run, tmp_path)
    assert load_config(run / "config.toml", {}).width == 1.0
    assert main([*fit, "--resume", "--width", "0.5"]) == 0
    result = json.loads((run / "results.json").read_text())
    assert result["size_search"]["traces"] >= 9, result["size_search"]
    judged = result["narrowing"]
    assert judged["earlier_width"] == 1.0 and judged["width"] == 0.5, judged
    kept = judged["kept"] == "new"
    assert kept == (judged["val_loss"] < judged["earlier_val_loss"]), judged
    assert load_config(run / "config.toml", {}).width == (0.5 if kept else 1.0)
    earlier = load_config(run / "config.toml", {}).width
    psnr = result["test_psnr"]
    assert main([*fit, "--resume", "--width", "4"]) == 0
    result = json.loads((run / "results.json").read_text())
    judged = result["narrowing"]
    assert judged["kept"] == "earlier", judged
    assert judged["earlier_val_loss"] < 0.8 * judged["val_loss"], judged
    assert load_config(run / "config.toml", {}).width == earlier
    assert abs(result["test_psnr"] - psnr) < 0.05, (result["test_psnr"], psnr)
    assert "narrowed_from" not in json.loads((run / "run.json").read_text())


def test_resume_with_another_width_refuses_an_adam_run(sphere_8x24, tmp_path, capsys):
    """Only a line search's level set is narrowed: an Adam run (the checked-in voxel run of
    tests/data/runs_v0) refuses --width on --resume, in one line, before it fits anything."""
    import shutil
    from pathlib import Path

    from clrefract.cli import main

    run = tmp_path / "adam"
    shutil.copytree(Path(__file__).parent / "data" / "runs_v0" / "voxel_adam", run)
    before = sorted(p.name for p in run.iterdir())
    args = ["fit", str(sphere_8x24), "--out", str(run), "--resume", "--width", "0.5"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "only a line search's level set" in err
    assert sorted(p.name for p in run.iterdir()) == before
