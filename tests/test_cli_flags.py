"""`clrefract fit`'s flags are FitConfig's keys: one each, its default in --help, its value
through load_config."""

import contextlib
import io
from dataclasses import fields

import pytest

from clrefract.cli import build_parser
from clrefract.fit import FitConfig
from clrefract.fit.config import CHOICES
from clrefract.fit.kinds import KINDS


def _fit_parser():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return sub.choices["fit"]


def test_every_config_key_is_a_fit_flag():
    flags = {a.dest: a.option_strings for a in _fit_parser()._actions}
    for f in fields(FitConfig):
        assert f.name in flags, f"no fit flag for {f.name}"
        assert f"--{f.name.replace('_', '-')}" in flags[f.name]
    assert "--growth-max" in flags["adjoint_growth_max"]  # the flag's older spelling
    assert set(CHOICES["field"]) == set(KINDS)


def test_fit_help_shows_every_default():
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        build_parser().parse_args(["fit", "--help"])
    text = "".join(out.getvalue().split())  # argparse wraps the lines, at hyphens too
    actions = {a.dest: a for a in _fit_parser()._actions}
    for f in fields(FitConfig):
        assert actions[f.name].option_strings[0] in text
        assert "(default:" in actions[f.name].help, f.name
        assert "".join(actions[f.name].help.replace("%%", "%").split()) in text, f.name
    assert text.count("(default:") >= len(fields(FitConfig))


def test_fit_flags_become_the_config(monkeypatch):
    args = build_parser().parse_args(
        ["fit", "DATA", "--out", "R", "--keep-growth", "5", "--line-steps", "0.01", "0.03",
         "--no-size-search", "--field-kind", "levelset", "--optimizer", "line-search"]
    )  # fmt: skip
    seen = {}

    def fake_run(dataset, out, cfg, resume, stream=None):
        seen["cfg"] = cfg
        return {}

    import clrefract.fit as fit

    monkeypatch.setattr(fit, "run_fit", fake_run)
    assert args.func(args) == 0  # the fit command, its run stubbed
    cfg = seen["cfg"]
    assert (cfg.keep_growth, cfg.line_steps, cfg.size_search) == (5.0, (0.01, 0.03), False)
    # flags not given leave the defaults (and the kind's and optimiser's)
    assert cfg.grad_sigma == FitConfig.grad_sigma and cfg.res == FitConfig.res
    assert cfg.iterations == fit.LINE_SEARCH_ITERATIONS
