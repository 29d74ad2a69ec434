"""Where a result came from: the package's version, the git commit it runs from, the command
line and when it began (run.json records them)."""

from __future__ import annotations

import functools
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

_command: list[str] | None = None
_started: str | None = None


def version() -> str:
    """The package's version, from its installed metadata ("unknown" where it is not installed)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("clrefract")
    except PackageNotFoundError:
        return "unknown"


@functools.cache
def git_state() -> tuple[str | None, bool | None]:
    """(commit, whether tracked files differ from it) of the git checkout the package runs
    from (its sources tracked there); (None, None) for an installed copy, or without git."""
    here = Path(__file__).resolve().parent

    def git(*args: str) -> str:
        done = subprocess.run(
            ["git", "-C", str(here), *args], capture_output=True, text=True, timeout=10
        )
        if done.returncode:
            raise OSError(done.stderr.strip())
        return done.stdout.strip()

    try:
        git("ls-files", "--error-unmatch", "__init__.py")  # a checkout of these sources
        commit = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return None, None
    return commit, bool(dirty)


def now() -> str:
    """The time now, UTC, ISO 8601 to the second."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def begin(argv: list[str]) -> None:
    """The command line's start: what it was asked (`argv`, after the program) and when."""
    global _command, _started
    _command, _started = ["clrefract", *argv], now()


def end() -> None:
    """The command line's end: later runs in this process (through the API) are not it."""
    global _command, _started
    _command = _started = None


def command() -> str:
    """The command line of this process (the command line's own, else sys.argv)."""
    argv = _command or [Path(sys.argv[0]).name, *sys.argv[1:]]
    return shlex.join(argv)


def started(default: str | None = None) -> str:
    """When the command began; `default` (else now) outside the command line."""
    return _started or default or now()
