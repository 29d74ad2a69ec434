"""The start search's losses, kept in the run folder as they come.

The search traces hundreds of candidate starts (7 to 10 minutes on the quick protocol).
Each loss is appended to `start_losses.jsonl` and flushed at once, so a start that is
interrupted, or fails after its search, leaves them behind; the same command run again
takes them up instead of tracing them again. The file's first line fingerprints what the
losses depend on (the settings, the dataset's files): losses of another start are dropped.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

NAME = "start_losses.jsonl"


def fingerprint(settings: str, dataset: Path, run: Path | None = None) -> str:
    """A digest of the run's settings and of the dataset's files (names, sizes, times),
    but for those of the `run` folder, which may lie inside the dataset's."""
    h = hashlib.sha256(settings.encode())
    root = Path(dataset).resolve()
    h.update(str(root).encode())
    skip = Path(run).resolve() if run is not None else None
    files = (p for p in root.rglob("*") if p.is_file())
    for path in sorted(p for p in files if skip is None or not p.is_relative_to(skip)):
        st = path.stat()
        h.update(f"{path.relative_to(root)}|{st.st_size}|{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


class StartLosses:
    """Losses by candidate key, read from and appended to `folder / NAME`."""

    def __init__(self, folder: Path, digest: str):
        self.path = Path(folder) / NAME
        self.known: dict[str, float] = {}
        self.reused = 0
        if self.path.is_file():
            self.known = _read(self.path, digest)
        if not self.known:
            self.path.write_text(json.dumps({"fingerprint": digest}) + "\n")
        self._earlier = set(self.known)
        self._file = self.path.open("a")

    def get(self, key: str) -> float | None:
        """The loss of a candidate already traced (`reused` counts those of earlier starts)."""
        if key in self._earlier:
            self._earlier.discard(key)
            self.reused += 1
        return self.known.get(key)

    def put(self, key: str, loss: float) -> None:
        self.known[key] = loss
        self._file.write(json.dumps({"key": key, "loss": loss}) + "\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def _read(path: Path, digest: str | None) -> dict[str, float]:
    """The losses of a file written for the same fingerprint (any, with None); {} for any
    other file. A last line cut short by the interruption is dropped."""
    out = {}
    try:
        lines = path.read_text().splitlines()
        head = json.loads(lines[0]) if lines else {}
        if not lines or (digest is not None and head.get("fingerprint") != digest):
            return {}
    except (OSError, ValueError, AttributeError):
        return {}
    for line in lines[1:]:
        try:
            row = json.loads(line)
            out[str(row["key"])] = float(row["loss"])
        except (ValueError, KeyError, TypeError):
            break
    return out


def count(folder: Path) -> int:
    """How many losses a run folder's file holds (0 without one)."""
    path = Path(folder) / NAME
    return len(_read(path, None)) if path.is_file() else 0
