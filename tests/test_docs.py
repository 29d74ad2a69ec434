"""The user's documentation stays true: README.md is a short guide that keeps the two set-up
commands CI runs, every `clrefract` command line shown in README.md and docs/ parses with the
real parser (in its current spelling), the generated references (docs/cli.md, docs/config.md)
are what tools/gen_docs.py writes, and the README's Python example runs."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import re
import shlex
from pathlib import Path

import pytest

from clrefract.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").rglob("*.md"))]
README_MAX_LINES = 300
# the README's set-up commands, exactly: CI (.ci/run) runs the second
SETUP_RENDER = (
    "bash tools/setup.sh && .venv/bin/clrefract render --field sphere --out renders/sphere"
)
SETUP_TESTS = "bash tools/setup.sh && .venv/bin/python -m pytest -q -n 2 --dist worksteal"
FENCE = re.compile(r"^\s*(```|~~~)")


def code_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line of a fenced code block, and of indented lines outside
    them (markdown's indented code), continuation lines joined to the line they continue."""
    out, fenced, lang = [], False, ""
    lines = text.splitlines()
    k = 0
    while k < len(lines):
        line, start = lines[k], k + 1
        k += 1
        m = FENCE.match(line)
        if m:
            fenced = not fenced
            lang = line.strip()[3:].strip().lower() if fenced else ""
            continue
        if fenced and lang in ("python", "py", "toml", "json", "text"):
            continue
        if not fenced and not line.startswith("    "):
            continue
        while line.rstrip().endswith("\\") and k < len(lines):
            line = line.rstrip()[:-1] + " " + lines[k].strip()
            k += 1
        out.append((start, line))
    return out


def clrefract_commands(text: str) -> list[tuple[int, list[str]]]:
    """(line number, arguments after `clrefract`) of every clrefract command line in the code
    blocks of a markdown text: `clrefract ...`, `.venv/bin/clrefract ...`, `python -m
    clrefract ...`, also after `&&`, `;`, `|` or a launcher (mpiexec, srun)."""
    found = []
    for lineno, line in code_lines(text):
        line = line.strip().removeprefix("$ ")
        try:
            words = shlex.split(line, comments=True)
        except ValueError as exc:
            raise AssertionError(f"line {lineno}: cannot split {line!r}: {exc}") from None
        pieces, piece = [], []
        for w in words:
            if w in ("&&", "||", ";", "|"):
                pieces.append(piece)
                piece = []
            else:
                piece.append(w)
        pieces.append(piece)
        for piece in pieces:
            for i, w in enumerate(piece):
                named = w == "clrefract" or w.endswith("/clrefract")
                module = w == "clrefract" and i > 0 and piece[i - 1] == "-m"
                if named or module:
                    found.append((lineno, piece[i + 1 :]))
                    break
    return found


def _parse(argv: list[str]) -> str:
    """Parse like `clrefract` (nothing runs); the parser's complaint, a deprecated spelling's
    warning, or '' where the line is good."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            build_parser().parse_args(argv)
        except SystemExit as exc:
            if exc.code not in (0, None):  # --help and --version exit 0
                return err.getvalue().strip() or f"exit status {exc.code}"
    return err.getvalue().strip() if "deprecated" in err.getvalue() else ""


def test_readme_is_a_short_guide():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines"


def test_readme_keeps_the_two_setup_commands():
    lines = [line.strip() for line in README.read_text(encoding="utf-8").splitlines()]
    assert SETUP_RENDER in lines
    assert SETUP_TESTS in lines
    ci = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert SETUP_TESTS in ci, "CI no longer runs the README's test command"


def test_the_extraction_finds_commands():
    text = "\n".join(
        [
            "Prose with clrefract fit in it.",
            "```bash",
            "clrefract dataset make sphere --out data/s  # a comment",
            "bash tools/setup.sh && .venv/bin/clrefract render \\",
            "    --field sphere",
            "mpiexec -n 4 clrefract eval runs/s",
            "```",
            "```python",
            "clrefract = 1",
            "```",
            "",
            "    python -m clrefract devices",
        ]
    )
    assert clrefract_commands(text) == [
        (3, ["dataset", "make", "sphere", "--out", "data/s"]),
        (4, ["render", "--field", "sphere"]),
        (6, ["eval", "runs/s"]),
        (12, ["devices"]),
    ]
    assert _parse(["fit", "data/s", "--out", "runs/s", "--iterations", "x"])
    assert _parse(["render", "--no-such-flag"])
    assert _parse(["render", "--res", "32"]) == ""
    assert "deprecated" in _parse(["fit", "data/s", "--out", "runs/s", "--field", "voxel"])


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_command_line_parses(page):
    commands = clrefract_commands(page.read_text(encoding="utf-8"))
    bad = [
        f"{page.name}:{n}: clrefract {shlex.join(a)}\n    {e}"
        for n, a in commands
        if (e := _parse(a))
    ]
    assert not bad, "command lines the parser refuses:\n" + "\n".join(bad)


def test_the_readme_shows_commands():
    commands = clrefract_commands(README.read_text(encoding="utf-8"))
    shown = {tuple(a[:2]) if a[0] in ("dataset", "table") else (a[0],) for _, a in commands}
    for needed in [("render",), ("dataset", "make"), ("fit",), ("eval",)]:
        assert needed in shown, f"README.md shows no `clrefract {' '.join(needed)}`"


LINK = re.compile(r"\]\(([^)\s]+)\)")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    """Every link to a file of the repository (README.md to docs/, docs/ to each other)
    names a file that exists; web links and anchors within a page are not checked."""
    targets = [m.group(1) for m in LINK.finditer(page.read_text(encoding="utf-8"))]
    missing = [
        t
        for t in targets
        if "://" not in t
        and not t.startswith(("#", "mailto:"))
        and not (page.parent / t.split("#")[0]).exists()
    ]
    assert not missing, f"{page.name} links to missing files: {missing}"


def test_generated_references_are_current():
    spec = importlib.util.spec_from_file_location("gen_docs", ROOT / "tools" / "gen_docs.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    stale = [str(p.relative_to(ROOT)) for p in gen.stale()]
    assert not stale, f"{', '.join(stale)} stale: run python tools/gen_docs.py"


def test_readme_python_example_runs(tmp_path, monkeypatch):
    text = README.read_text(encoding="utf-8")
    section = text.split("## Python API", 1)[1]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert blocks, "README.md's Python API section has no python block"
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(blocks[0], "README.md (Python API)", "exec"), scope)  # noqa: S102
    image = scope["image"]
    assert image.ndim == 3 and image.shape[2] == 3 and image.min() >= 0
