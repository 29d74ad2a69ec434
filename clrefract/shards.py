"""Benchmark runs spread over processes or cluster jobs: `--shard i/n` runs every n-th item
from the i-th and writes its own results file; `--merge` puts the shards' rows back in the
suite's order.

A benchmark's runs are independent fits, so they need no MPI: n jobs of an array (Slurm's
SLURM_ARRAY_TASK_ID, or SLURM_PROCID under srun) each take one shard.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from .errors import ClrefractError


def parse(spec: str) -> tuple[int, int]:
    """'i/n' -> (i, n) with 0 <= i < n; '' -> (0, 1), the whole suite."""
    if not spec:
        return 0, 1
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", spec)
    if not m or not int(m[1]) < int(m[2]):
        raise ClrefractError(f"--shard takes i/n with 0 <= i < n, got {spec!r}")
    return int(m[1]), int(m[2])


def select(items: list, spec: str) -> list:
    """The shard's items: every n-th from the i-th (round-robin: the suites list similar
    scenes together, so each shard gets a mix of fast and slow ones)."""
    i, n = parse(spec)
    return list(items)[i::n]


def path_for(path: str | Path, spec: str) -> Path:
    """Where a shard writes: results.json -> results.shard-1-of-4.json."""
    path = Path(path)
    i, n = parse(spec)
    return path if n == 1 else path.with_suffix(f".shard-{i}-of-{n}{path.suffix}")


def merge(path: str | Path, order: list, key: str = "scene", rows: str = "scenes") -> dict:
    """The shards' results files beside `path`, as one: their rows in `order` (rows of items
    not in it go last), the first shard's other entries. Refuses an incomplete set."""
    path = Path(path)
    found = sorted(path.parent.glob(f"{path.stem}.shard-*-of-*{path.suffix}"))
    if not found:
        raise ClrefractError(f"no shard results beside {path} ({path.stem}.shard-i-of-n)")
    counts = {int(re.search(r"-of-(\d+)", p.name)[1]) for p in found}
    if len(counts) != 1 or len(found) != counts.pop():
        names = ", ".join(p.name for p in found)
        raise ClrefractError(f"an incomplete or mixed set of shards: {names}")
    parts = [json.loads(p.read_text()) for p in found]
    all_rows = [r for part in parts for r in part[rows]]
    rank = {name: k for k, name in enumerate(order)}
    all_rows.sort(key=lambda r: rank.get(r[key], len(rank)))
    return {**parts[0], rows: all_rows, "shards": [p.name for p in found]}
