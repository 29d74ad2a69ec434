"""Index fields: analytic, voxel grid, hash grid + MLP; and parsing of user field specs."""

from __future__ import annotations

import json
from pathlib import Path

from ..errors import ClrefractError
from .analytic import ANALYTIC
from .base import Box, Field

__all__ = ["ANALYTIC", "Box", "Field", "field_from_dict", "field_from_spec", "load_field_file"]


def field_from_dict(d: dict) -> Field:
    """An analytic field from {'kind': ..., parameter: value}."""
    d = dict(d)
    kind = d.pop("kind", None)
    if kind == "graded-glass":
        from .interior import GradedInterface

        return GradedInterface.from_dict({"kind": kind, **d})
    cls = ANALYTIC.get(kind)
    if cls is None:
        # the family shapes (scene.json of their datasets): ground truth for eta metrics
        from ..family import SHAPES

        cls = SHAPES.get(kind)
    if cls is None:
        raise ClrefractError(
            f"unknown field kind {kind!r}; analytic kinds are {', '.join(ANALYTIC)}, "
            "or give a voxel/hash-grid .npz file"
        )
    try:
        return cls(
            **{
                k: tuple(v) if isinstance(v, list) and k in ("center", "tilt") else v
                for k, v in d.items()
            }
        )
    except TypeError as exc:
        raise ClrefractError(f"bad parameters for field {kind!r}: {exc}") from None


def _value(text: str):
    parts = text.split("/")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ClrefractError(f"field parameter value {text!r} is not a number") from None
    return vals[0] if len(vals) == 1 else vals


def load_field_file(path: Path, box: Box | None = None) -> Field:
    """A field saved as .npz (voxel grid or hash grid) or described in .json."""
    if not path.is_file():
        raise ClrefractError(f"{path}: field file not found")
    if path.suffix == ".json":
        try:
            return field_from_dict(json.loads(path.read_text()))
        except json.JSONDecodeError as exc:
            raise ClrefractError(f"{path}: not valid JSON ({exc})") from None
    if path.suffix == ".npz":
        import numpy as np

        try:
            with np.load(path, allow_pickle=False) as z:
                kind = str(z["kind"]) if "kind" in z else "voxel"
        except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's to fix
            raise ClrefractError(f"{path}: cannot read field file ({exc})") from None
        if kind == "levelset":
            from .levelset import LevelSetField

            return LevelSetField.load(path)
        if kind in ("interface", "polytope"):
            from .interface import InterfaceField, PolytopeInterface
            from .interior import GradedInterface

            cls = InterfaceField if kind == "interface" else PolytopeInterface
            return GradedInterface.wrap_loaded(cls.load(path), path)
        if kind == "hashgrid":
            from .hashgrid import HashGridField

            return HashGridField.load(path)
        from .voxel import VoxelGrid

        return VoxelGrid.load(path)
    raise ClrefractError(f"{path}: unknown field file type (expected .npz or .json)")


def field_from_spec(spec: str, box: Box | None = None) -> Field:
    """'sphere', 'sphere:radius=20,eta=1.5,width=1', 'blobs:centers=0/0/0', or a file path."""
    p = Path(spec)
    if p.suffix in (".npz", ".json") or p.exists():
        return load_field_file(p, box)
    kind, _, rest = spec.partition(":")
    d: dict = {"kind": kind.strip()}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, val = item.partition("=")
        if not eq:
            raise ClrefractError(f"field spec {spec!r}: expected key=value, got {item!r}")
        d[key.strip()] = _value(val.strip())
    if d["kind"] == "blobs":
        for key in ("centers", "amplitudes", "sigmas"):
            if key in d and not isinstance(d[key], list):
                d[key] = [d[key]]
    return field_from_dict(d)
