"""The conventions a command line is expected to keep: --version, every default in help, one
meaning per flag name (renamed flags keep their old spelling, deprecated), --quiet and
--verbose, and `render --orbit`."""

from __future__ import annotations

import argparse
import contextlib
import io
import json

import imageio.v3 as iio
import pytest

from clrefract.cli import build_parser, main
from clrefract.provenance import version


def _parsers(parser, name="clrefract"):
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, p in action.choices.items():
                yield from _parsers(p, f"{name} {sub}")


def test_version(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.strip() == f"clrefract {version()}"
    assert version() != "unknown"  # the package's metadata


def test_every_help_shows_every_default():
    for name, parser in _parsers(build_parser()):
        text = " ".join(parser.format_help().split())
        fmt = parser.formatter_class(name)
        for a in parser._actions:
            valued = a.default not in (None, argparse.SUPPRESS, False) and a.option_strings
            if not valued or isinstance(a, argparse._StoreConstAction | argparse._VersionAction):
                continue
            assert "(default" in fmt._get_help_string(a), (name, a.option_strings)
            assert a.option_strings[0] in text


def test_one_meaning_per_flag_name():
    """Each option name means one thing in every command that has it: a deprecated old
    spelling aside, the renamed flags are fit's --grid-res and --field-kind and import's
    --pose-box; render keeps --field (a field spec) and --res (an image's size)."""
    seen: dict[str, set[str]] = {}
    for name, parser in _parsers(build_parser()):
        for a in parser._actions:
            old = getattr(a, "old_spellings", ())
            for s in a.option_strings:
                if s not in old and s not in ("-h", "--help"):
                    seen.setdefault(s, set()).add(name)
    assert seen["--res"] == {"clrefract render", "clrefract dataset make"}
    assert seen["--field"] == {"clrefract render"}
    assert seen["--grid-res"] == seen["--field-kind"] == {"clrefract fit"}
    assert seen["--box"] == {
        "clrefract fit",
        "clrefract dataset check",
        "clrefract dataset register-env",
    }
    assert seen["--pose-box"] == {"clrefract dataset import"}


@pytest.mark.parametrize(
    "old, new, dest, value",
    [
        (["fit", "D", "--out", "R", "--res", "16"], "--grid-res", "res", 16),
        (["fit", "D", "--out", "R", "--field", "voxel"], "--field-kind", "field", "voxel"),
        (["dataset", "import", "S", "--out", "O", "--box", "0,0,0,1,1,1"], "--pose-box",
         "box", ["0,0,0,1,1,1"]),
    ],
)  # fmt: skip
def test_old_spellings_still_work_and_say_so(old, new, dest, value):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        args = build_parser().parse_args(old)
    assert getattr(args, dest) == value
    assert err.getvalue().count("\n") == 1
    assert "deprecated" in err.getvalue() and new in err.getvalue()
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        args = build_parser().parse_args([new if a == old[-2] else a for a in old])
    assert getattr(args, dest) == value and err.getvalue() == ""


def test_readme_set_up_command_parses_without_a_warning(capsys):
    args = build_parser().parse_args(["render", "--field", "sphere", "--out", "renders/sphere"])
    assert args.field == "sphere" and capsys.readouterr().err == ""


def test_quiet_and_verbose_go_before_or_after_the_command():
    p = build_parser()
    assert p.parse_args(["-q", "devices"]).quiet
    assert p.parse_args(["devices", "--quiet"]).quiet
    assert p.parse_args(["devices", "-v"]).verbose and not p.parse_args(["devices", "-v"]).quiet
    with pytest.raises(SystemExit), contextlib.redirect_stderr(io.StringIO()):
        p.parse_args(["--quiet", "--verbose", "devices"])


def test_a_quiet_command_leaves_the_callers_bars_and_level_as_they_were(capsys):
    """`main([..., "-q"])` in a process that goes on (a test, a notebook): its progress bars
    and log level come back afterwards. A quiet call once hid every later bar in its pytest
    worker, and a start's progress test failed by the order tests ran in."""
    import logging

    from clrefract.log import Progress

    logger = logging.getLogger("clrefract")
    level = logger.level
    assert main(["-q", "devices"]) == 0
    capsys.readouterr()
    bar = Progress(3, "after", stream=io.StringIO())
    assert not bar.disable
    bar.close()
    assert logger.level == level


def test_render_orbit_writes_frames_and_a_gif(tmp_path, capsys):
    out = tmp_path / "orbit"
    args = ["render", "--field", "sphere", "--orbit", "4", "--res", "12", "--step", "2"]
    assert main([*args, "--out", str(out)]) == 0
    assert "orbit.gif" in capsys.readouterr().err
    frames = sorted(p.name for p in out.glob("*.png"))
    assert frames == [f"orbit_{k:03d}.png" for k in range(4)]
    gif = iio.imread(out / "orbit.gif", index=None)
    assert gif.shape[:3] == (4, 12, 12)
    # the object turns: the frames differ
    assert (gif[0] != gif[1]).any()
    views = json.loads((out / "render.json").read_text())["views"]
    assert [v["view"] for v in views] == [f"orbit_{k:03d}" for k in range(4)]
    # --quiet: the render says nothing
    assert main(["--quiet", *args, "--out", str(tmp_path / "q")]) == 0
    assert capsys.readouterr().err == ""
    assert main([*args, "--cameras", "c.json", "--out", str(tmp_path / "x")]) == 2
    assert "--orbit places its own cameras" in capsys.readouterr().err
