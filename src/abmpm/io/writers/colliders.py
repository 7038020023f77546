"""``colliders/collider_NNNNN.ply``: the triangles of all the scene's colliders at
every output frame (binary PLY; scenes with colliders)."""

from __future__ import annotations

from abmpm.io.outdir import collider_path
from abmpm.io.ply import write_mesh_ply
from abmpm.io.writers.base import FrameData, RunContext, Writer


class ColliderMeshWriter(Writer):
    name = "colliders"

    def begin(self, run: RunContext) -> None:
        self.out = run.out
        mesh = run.collider_mesh
        self.faces = None if mesh is None else mesh[1]

    def write_frame(self, frame: int, data: FrameData) -> None:
        if self.faces is not None and data.output_frame:
            write_mesh_ply(collider_path(self.out, frame), data.collider_vertices, self.faces)
