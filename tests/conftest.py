"""Datasets that several tests read: each made once per session (once per pytest-xdist
worker), in a folder of its own that no test may write into. A fit writes into its own run
folder; a test that would damage a dataset copies it first. Each test that takes one checks,
as it ends, that the folder holds the same files with the same bytes as when it was made."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest

from clrefract.parallel import share_cores

# pytest-xdist's workers split the cores rather than each PoCL starting a thread per core
if "PYTEST_XDIST_WORKER_COUNT" in os.environ:
    share_cores(int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))


def folder_digest(root: Path) -> str:
    """Every path under root (folders included) and every file's bytes, hashed."""
    h = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        h.update(str(path.relative_to(root)).encode() + b"\0")
        if path.is_file():
            h.update(path.read_bytes())
    return h.hexdigest()


def _make(tmp_path_factory, name: str, kind: str, **options) -> tuple[Path, str]:
    from clrefract.synth import MakeOptions, make_dataset

    root = tmp_path_factory.mktemp("shared") / name
    make_dataset(kind, root, MakeOptions(**options))
    return root, folder_digest(root)


_DAMAGED: set[Path] = set()  # shared datasets a test on this worker has written into


def _unchanged(made: tuple[Path, str]):
    root, digest = made
    yield root
    if root in _DAMAGED:
        raise AssertionError(f"the shared dataset {root} was written into by an earlier test")
    if folder_digest(root) != digest:
        _DAMAGED.add(root)
        raise AssertionError(f"this test wrote into the shared dataset {root}")


@pytest.fixture(scope="session")
def _sphere_25x48(tmp_path_factory):
    return _make(
        tmp_path_factory, "sphere", "sphere", views=25, res=48, env_width=512, volume_res=16
    )


@pytest.fixture
def sphere_25x48(_sphere_25x48):
    """A glass sphere (radius 20 mm, index 1.5) in 25 views of 48 x 48 pixels: 20 to train
    on, 5 to test on. Read-only."""
    yield from _unchanged(_sphere_25x48)


@pytest.fixture(scope="session")
def _sphere_10x24(tmp_path_factory):
    return _make(
        tmp_path_factory, "sphere", "sphere", views=10, res=24, env_width=256, volume_res=16
    )


@pytest.fixture
def sphere_10x24(_sphere_10x24):
    """The glass sphere in 10 views of 24 x 24 pixels: 8 to train on, views 0 and 5 to test
    on. Read-only."""
    yield from _unchanged(_sphere_10x24)


@pytest.fixture(scope="session")
def _sphere_12x24(tmp_path_factory):
    return _make(
        tmp_path_factory, "sphere", "sphere", views=12, res=24, env_width=256, volume_res=16
    )


@pytest.fixture
def sphere_12x24(_sphere_12x24):
    """The glass sphere in 12 views of 24 x 24 pixels: 9 to train on (a fit with val_views
    holds one of them out), 3 to test on; the small fits' dataset. Read-only."""
    yield from _unchanged(_sphere_12x24)


@pytest.fixture(scope="session")
def _sphere_8x24(tmp_path_factory):
    return _make(tmp_path_factory, "sphere", "sphere", views=8, res=24, env_width=256, volume_res=8)


@pytest.fixture
def sphere_8x24(_sphere_8x24):
    """The glass sphere in 8 views of 24 x 24 pixels (its truth on 8^3 nodes): 6 to train
    on, 2 to test on; the command-line runs' dataset. Read-only."""
    yield from _unchanged(_sphere_8x24)
