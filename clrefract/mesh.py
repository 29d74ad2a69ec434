"""Triangle meshes in and out (ground-truth surfaces, extracted surfaces) through trimesh:
PLY (ASCII and binary, either byte order, any index type), OBJ, STL and the other formats
trimesh reads. A file that cannot be read is refused in one line that names it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import ClrefractError
from .imageio import PathLike, atomic_path

FORMATS = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf")


def _trimesh():
    try:
        import trimesh
    except ImportError:
        raise ClrefractError(
            "reading and writing meshes needs trimesh: pip install trimesh"
        ) from None
    return trimesh


def read_mesh(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float64 and triangles (m, 3) int64 of a mesh file; a scene of several
    meshes is joined into one."""
    path = Path(path)
    if not path.is_file():
        raise ClrefractError(f"{path}: mesh file not found")
    if path.suffix.lower() not in FORMATS:
        raise ClrefractError(
            f"{path}: unknown mesh format {path.suffix or '(no extension)'} "
            f"(known: {', '.join(FORMATS)})"
        )
    trimesh = _trimesh()
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
        verts = np.asarray(mesh.vertices, np.float64)
        faces = np.asarray(mesh.faces, np.int64)
    except Exception as exc:  # noqa: BLE001 - trimesh and its parsers raise anything
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ClrefractError(f"{path}: not a readable mesh ({msg})") from None
    return _checked(path, verts, faces)


def _checked(path: Path, verts: np.ndarray, faces: np.ndarray):
    if verts.ndim != 2 or verts.shape[1] != 3 or len(faces) == 0:
        raise ClrefractError(f"{path}: mesh has no triangles")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ClrefractError(f"{path}: mesh faces are not triangles")
    if not np.isfinite(verts).all():
        raise ClrefractError(f"{path}: mesh has non-finite vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise ClrefractError(f"{path}: mesh faces index vertices that do not exist")
    return verts, faces


def write_mesh(path: PathLike, verts: np.ndarray, faces: np.ndarray) -> None:
    """A triangle mesh, atomically, in the format of the file's extension (PLY: binary)."""
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ClrefractError(f"{path}: unknown mesh format (known: {', '.join(FORMATS)})")
    trimesh = _trimesh()
    mesh = trimesh.Trimesh(np.asarray(verts, np.float64), np.asarray(faces), process=False)
    with atomic_path(path, suffix=path.suffix) as tmp:
        mesh.export(tmp)
