"""Output files: PLY particles, checkpoints, JSON summaries, USD points.

These modules know nothing of the solver; they take numpy arrays and dicts.
:mod:`abmpm.io.outdir` is the layout of a run's output folder,
:mod:`abmpm.io.writers` the writers that turn a running Simulation (its public
interface only) into those files, one per kind of output.
"""

from abmpm.io.atomic import atomic_write
from abmpm.io.checkpoint import latest_checkpoint, load_checkpoint, save_checkpoint
from abmpm.io.ply import (
    read_mesh_ply,
    read_particles_ply,
    write_mesh_ply,
    write_particles_ply,
)
from abmpm.io.summary import to_builtin, write_json
from abmpm.io.usd import UsdPointsWriter

__all__ = [
    "atomic_write",
    "latest_checkpoint",
    "load_checkpoint",
    "read_mesh_ply",
    "read_particles_ply",
    "save_checkpoint",
    "to_builtin",
    "UsdPointsWriter",
    "write_json",
    "write_mesh_ply",
    "write_particles_ply",
]
