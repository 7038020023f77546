"""Binary little-endian PLY particle files (via ``plyfile``)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import trimesh
from plyfile import PlyData, PlyElement, PlyParseError

from abmpm.errors import OutputError
from abmpm.io.atomic import atomic_write

_AXES = ("x", "y", "z")


def _column_dtype(a: np.ndarray) -> str:
    if a.dtype == np.uint8:
        return "u1"
    if a.dtype == np.bool_:
        return "u1"
    if np.issubdtype(a.dtype, np.integer):
        return "i4"
    if np.issubdtype(a.dtype, np.floating):
        return "f4"
    raise OutputError(f"PLY attribute of unsupported dtype {a.dtype}")


def _vector_names(name: str) -> tuple[str, str, str]:
    if name == "v":
        return ("vx", "vy", "vz")
    return tuple(f"{name}_{c}" for c in _AXES)  # type: ignore[return-value]


def write_particles_ply(
    path: str | os.PathLike,
    x: np.ndarray,
    attributes: dict[str, np.ndarray] | None = None,
) -> None:
    """Write particles as a binary little-endian PLY point cloud (atomic).

    The ``vertex`` element has ``x y z`` (float32) then one property per attribute
    column: an (N,3) array ``name`` becomes ``name_x name_y name_z`` (``v`` becomes
    ``vx vy vz``); (N,) floats are float32, ints int32, uint8/bool stay uint8.
    """
    path = Path(path)
    x = np.asarray(x)
    if x.ndim != 2 or x.shape[1] != 3:
        raise OutputError(f"{path}: positions must have shape (N, 3), got {x.shape}")
    n = x.shape[0]
    columns: list[tuple[str, str, np.ndarray]] = [
        (c, "f4", x[:, i]) for i, c in enumerate(_AXES)
    ]
    for name, arr in (attributes or {}).items():
        a = np.asarray(arr)
        if a.shape[0] != n:
            raise OutputError(
                f"{path}: attribute {name!r} has {a.shape[0]} rows, expected {n}"
            )
        dt = _column_dtype(a)
        if a.ndim == 1:
            columns.append((name, dt, a))
        elif a.ndim == 2 and a.shape[1] == 3:
            for i, cname in enumerate(_vector_names(name)):
                columns.append((cname, dt, a[:, i]))
        else:
            raise OutputError(
                f"{path}: attribute {name!r} must have shape (N,) or (N, 3), got {a.shape}"
            )
    names = [c[0] for c in columns]
    if len(set(names)) != len(names):
        raise OutputError(f"{path}: duplicate PLY property names {names}")
    vertex = np.empty(n, dtype=[(c[0], "<" + c[1]) for c in columns])
    for cname, _, col in columns:
        vertex[cname] = col
    element = PlyElement.describe(vertex, "vertex")
    with atomic_write(path) as tmp:
        PlyData([element], text=False, byte_order="<").write(str(tmp))


def read_particles_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a particle PLY written by :func:`write_particles_ply`.

    Returns ``{"x": (N,3) float32, ...}`` with vector attributes regrouped into
    (N,3) arrays (``vx vy vz`` -> ``"v"``, ``name_x name_y name_z`` -> ``name``).
    """
    path = Path(path)
    try:
        ply = PlyData.read(str(path))
        data = ply["vertex"].data
    except (OSError, ValueError, KeyError, PlyParseError) as exc:  # a damaged or foreign file
        why = "no vertex element" if isinstance(exc, KeyError) else exc
        raise OutputError(f"cannot read PLY file {path}: {why}") from None
    names = list(data.dtype.names)
    missing = [c for c in _AXES if c not in names]
    if missing:
        raise OutputError(f"cannot read PLY file {path}: its vertices have no {', '.join(missing)}")
    out: dict[str, np.ndarray] = {}
    used: set[str] = set()
    out["x"] = np.stack([np.asarray(data[c]) for c in _AXES], axis=1)
    used.update(_AXES)
    for name in names:
        if name in used:
            continue
        group = None
        if name == "vx":
            group = ("v", ("vx", "vy", "vz"))
        elif name.endswith("_x"):
            base = name[:-2]
            group = (base, _vector_names(base))
        if group is not None and all(c in names for c in group[1]):
            out[group[0]] = np.stack([np.asarray(data[c]) for c in group[1]], axis=1)
            used.update(group[1])
        else:
            out[name] = np.asarray(data[name]).copy()
            used.add(name)
    return out


def write_mesh_ply(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a triangle mesh as a binary little-endian PLY (via trimesh, atomic).

    ``vertices`` (V, 3) are stored as float32, ``faces`` (F, 3) as int32 vertex
    indices; the order of both is kept, so files of the same collider at different
    times share the face list and can be loaded as a deforming mesh.
    """
    path = Path(path)
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = np.ascontiguousarray(faces, dtype=np.int32)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise OutputError(f"{path}: expected (V, 3) vertices and (F, 3) faces, got {v.shape} and {f.shape}")
    mesh = trimesh.Trimesh(vertices=v, faces=f, process=False, validate=False)
    data = mesh.export(file_type="ply", encoding="binary")
    with atomic_write(path) as tmp:
        tmp.write_bytes(data)


def read_mesh_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh PLY written by :func:`write_mesh_ply`: ``(vertices, faces)``
    as float64 (V, 3) and int64 (F, 3), in file order."""
    path = Path(path)
    try:
        mesh = trimesh.load(str(path), file_type="ply", process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for a corrupt file
        raise OutputError(f"cannot read PLY mesh {path}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise OutputError(f"cannot read PLY mesh {path}: no triangles in the file")
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
