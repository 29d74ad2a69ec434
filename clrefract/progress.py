"""A dependency-free progress bar on stderr: count, rate, time left, and extra figures."""

from __future__ import annotations

import sys
import time


class Progress:
    def __init__(self, total: int, label: str = "", unit: str = "it", stream=None):
        self.total, self.label, self.unit = max(int(total), 1), label, unit
        self.stream = stream or sys.stderr
        self.start = time.perf_counter()
        self.done = 0
        self._last = 0.0
        self.tty = getattr(self.stream, "isatty", lambda: False)()

    def update(self, n: int = 1, **figures) -> None:
        self.done += n
        now = time.perf_counter()
        # redraw at most 10 times a second on a terminal, once every 5 s in logs
        if self.done < self.total and now - self._last < (0.1 if self.tty else 5.0):
            return
        self._last = now
        elapsed = now - self.start
        rate = self.done / elapsed if elapsed > 0 else 0.0
        left = (self.total - self.done) / rate if rate > 0 else 0.0
        frac = self.done / self.total
        bar = "#" * int(24 * frac) + "-" * (24 - int(24 * frac))
        extra = "  ".join(f"{k} {_fmt(v)}" for k, v in figures.items())
        line = (
            f"{self.label} [{bar}] {self.done}/{self.total} {rate:.3g} {self.unit}/s "
            f"{_clock(elapsed)} elapsed, {_clock(left)} left  {extra}"
        ).rstrip()
        end = "\n" if (not self.tty or self.done >= self.total) else ""
        self.stream.write(("\r" if self.tty else "") + line + end)
        self.stream.flush()


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _clock(seconds: float) -> str:
    m, s = divmod(int(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"
