"""Messages and progress bars: one `clrefract` logger on stderr (INFO; WARNING and above
under --quiet, DEBUG under --verbose) and tqdm bars, which --quiet turns off.

The command line's results (a table, a JSON summary) go to stdout with print; what it says
about its work goes through `logger`; errors stay one line, `clrefract: error: ...`."""

from __future__ import annotations

import logging
import sys
from contextlib import contextmanager

from tqdm import tqdm

logger = logging.getLogger("clrefract")
_bars = True  # off under --quiet


class _StderrHandler(logging.StreamHandler):
    """Writes to sys.stderr as it is when a message comes (pytest swaps it), clearing any
    progress bar first and drawing it again after."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):
        pass

    def emit(self, record):
        with tqdm.external_write_mode(file=sys.stderr):
            super().emit(record)


class _Format(logging.Formatter):
    def format(self, record):
        text = record.getMessage()
        if record.levelno >= logging.WARNING:
            text = f"{record.levelname.lower()}: {text}"
        return text


def configure(quiet: bool = False, verbose: bool = False) -> None:
    """The command line's logging: INFO on stderr, WARNING under `quiet` (and no bars),
    DEBUG under `verbose`."""
    global _bars
    _bars = not quiet
    logger.setLevel(logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO)
    if not any(isinstance(h, _StderrHandler) for h in logger.handlers):
        handler = _StderrHandler()
        handler.setFormatter(_Format())
        logger.addHandler(handler)
    logger.propagate = False


@contextmanager
def configured(quiet: bool = False, verbose: bool = False):
    """configure() for one command: an in-process caller (a test, a notebook) has its bars
    and level back after it."""
    global _bars
    saved = _bars, logger.level
    configure(quiet, verbose)
    try:
        yield
    finally:
        _bars = saved[0]
        logger.setLevel(saved[1])


class LogStream:
    """A text stream whose lines go to `logger` (a fit's stream under the command line):
    a line that starts with 'warning: ' as a warning, the others as information."""

    def __init__(self):
        self._part = ""

    def write(self, text: str) -> int:
        lines = (self._part + text).split("\n")
        self._part = lines.pop()
        for line in lines:
            if line.startswith("warning: "):
                logger.warning(line[len("warning: ") :])
            else:
                logger.info(line)
        return len(text)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return _isatty(sys.stderr)


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


class Progress(tqdm):
    """A tqdm bar on stderr (or `stream`): update(n, **figures) shows the figures after the
    count, `done` is the count so far, and the bar closes itself at its total. A terminal
    redraws it at most 10 times a second, a log once every 5 s; --quiet hides it."""

    monitor_interval = 0  # no monitor thread

    def __init__(self, total: int, label: str = "", unit: str = "it", stream=None, initial=0):
        if stream is None or isinstance(stream, LogStream):
            stream = sys.stderr
        tty = _isatty(stream)
        super().__init__(
            total=max(int(total), 1),
            desc=label or None,
            unit=unit,
            file=stream,
            initial=initial,
            disable=not _bars,
            mininterval=0.1 if tty else 5.0,
            dynamic_ncols=tty,
            leave=True,
        )

    @property
    def done(self) -> int:
        return self.n

    def update(self, n: int = 1, **figures):
        if figures:
            self.set_postfix({k: _fmt(v) for k, v in figures.items()}, refresh=False)
        if self.disable:
            self.n += n  # a hidden (or closed) bar still counts
        else:
            super().update(n)
            if self.n >= self.total:
                self.close()
