"""Surface meshes of the particles, one per material and frame.

The particles are turned into a triangle mesh by splashsurf (``pysplashsurf``): an
SPH estimate of the volume fraction on a grid, and marching cubes at its
``iso`` level. Fluids get splashsurf's weighted Laplacian smoothing and barnacle
decimation (Löschner et al. 2023), which removes the particle-size bumps of a
free surface, and a wider kernel (3 particle radii against 2): MPM fluid spreads
thin where it splashes (particles up to twice their rest volume apart), and the
narrow kernel meshes such a sheet as Swiss cheese. Solids keep the narrow kernel
and the plain marching-cubes surface (``solid_smoothing_iters = 0`` by default),
so a thin strip stays thin and the edges of a cut stay sharp.

Lengths are set from the particle spacing ``s`` (the cube root of a particle's
volume, mass over rest density): splashsurf's particle radius is
``radius * s``; its kernel and its marching-cubes cell are given in particle radii.
With the defaults (radius 0.5 s, cubes of 1 radius, iso 0.6) the mesh of a resting
sphere of particles encloses its volume to within 2% (``tests/test_surface.py``
holds it to 3%).

Adaptive runs hold particles of two sizes, and splashsurf takes one radius. A
coarse particle of a group that also holds subdivided ones is therefore stood in
for by its ``b^3`` lattice children (the positions a split would give them) for
the reconstruction only, and the whole group is meshed at the fine spacing.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from abmpm.errors import OutputError
from abmpm.io.outdir import SURFACE_RE, SURFACES_DIR
from abmpm.io.ply import write_mesh_ply

__all__ = ["SURFACES_DIR", "SurfaceMesh", "file_stem", "import_splashsurf", "surface_meshes", "surface_path", "surfaces_of_folder", "write_surfaces"]



@dataclass
class SurfaceMesh:
    """The surface of one material at one frame."""

    material: str
    vertices: np.ndarray  # (V, 3) float32
    faces: np.ndarray  # (F, 3) int32


def surface_path(out_dir: str | Path, frame: int, material: str) -> Path:
    return Path(out_dir) / SURFACES_DIR / f"surface_{frame:05d}_{file_stem(material)}.ply"


def file_stem(name: str) -> str:
    """A material name as it stands in a surface file's name."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name) or "material"


def import_splashsurf():
    """The pysplashsurf module, or an OutputError saying how to install it."""
    try:
        import pysplashsurf
    except ImportError as exc:
        raise OutputError("surface meshes need pysplashsurf: pip install 'abmpm[surface]'") from exc
    return pysplashsurf


def _spacings(mass: np.ndarray, density: np.ndarray) -> np.ndarray:
    return np.cbrt(mass.astype(np.float64) / density)


def _one_size(x: np.ndarray, spacing: np.ndarray) -> tuple[np.ndarray, float]:
    """Positions standing for the group at one spacing (the finest present): a coarser
    particle is replaced by the ``b^3`` centres of a cube of side ``b`` fine spacings."""
    fine = float(spacing.min())
    ratio = np.rint(spacing / fine).astype(np.int64)
    if np.all(ratio == 1):
        return x, fine
    parts = [x[ratio == 1]]
    for b in np.unique(ratio[ratio > 1]):
        offsets = (np.stack(np.meshgrid(*(np.arange(b),) * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) / b - 0.5
        centres = x[ratio == b]
        parts.append((centres[:, None, :] + offsets[None, :, :] * (b * fine)).reshape(-1, 3))
    return np.concatenate(parts), fine


def reconstruct(x: np.ndarray, spacing: float, options, fluid: bool) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of the surface of particles ``x`` at ``spacing``, with the
    scene's ``[output.surface_mesh]`` options."""
    ps = import_splashsurf()
    iters = options.fluid_smoothing_iters if fluid else options.solid_smoothing_iters
    length = options.fluid_smoothing_length if fluid else options.solid_smoothing_length
    smooth = dict(mesh_smoothing_iters=iters, mesh_smoothing_weights=True, decimate_barnacles=True) if iters else {}
    mesh, _ = ps.reconstruction_pipeline(
        np.ascontiguousarray(x, dtype=np.float64),
        particle_radius=options.radius * spacing,
        smoothing_length=length,
        cube_size=options.cube_size,
        iso_surface_threshold=options.iso,
        mesh_cleanup=True,
        **smooth,
    )
    return np.asarray(mesh.mesh.vertices, dtype=np.float32), np.asarray(mesh.mesh.triangles, dtype=np.int32)


def surface_meshes(frame: dict, scene) -> list[SurfaceMesh]:
    """The surface of every material that has particles in ``frame`` (a frame as
    :func:`abmpm.io.read_particles_ply` reads it: x, material, mass, ...)."""
    options = scene.output.surface_mesh
    materials = scene.materials
    density = np.array([m.density for m in materials], dtype=np.float64)
    mat = frame["material"].astype(np.int64)
    out = []
    for i, m in enumerate(materials):
        sel = mat == i
        if np.count_nonzero(sel) < 4:
            continue
        x, spacing = _one_size(frame["x"][sel].astype(np.float64), _spacings(frame["mass"][sel], density[i]))
        v, f = reconstruct(x, spacing, options, fluid=m.model == "fluid")
        if len(f):
            out.append(SurfaceMesh(m.name, v, f))
    return out


def write_surfaces(out_dir: Path, frame: int, meshes: list[SurfaceMesh]) -> list[Path]:
    """Write the meshes of one frame as ``surfaces/surface_NNNNN_<material>.ply``."""
    paths = []
    for s in meshes:
        p = surface_path(out_dir, frame, s.material)
        write_mesh_ply(p, s.vertices, s.faces)
        paths.append(p)
    return paths


def surfaces_of_folder(out_dir: Path) -> dict[int, dict[str, Path]]:
    """{frame: {material: path}} of the surface PLYs in a run's folder."""
    found: dict[int, dict[str, Path]] = {}
    folder = Path(out_dir) / SURFACES_DIR
    if folder.is_dir():
        for p in sorted(folder.iterdir()):
            m = SURFACE_RE.match(p.name)
            if m and p.is_file():
                found.setdefault(int(m.group(1)), {})[m.group(2)] = p
    return found
