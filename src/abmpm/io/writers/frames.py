"""``frames/frame_NNNNN.ply``: the particles of every output frame (binary PLY)."""

from __future__ import annotations

from abmpm.io.outdir import frame_path
from abmpm.io.ply import write_particles_ply
from abmpm.io.writers.base import FrameData, RunContext, Writer


class ParticleFrameWriter(Writer):
    """Positions plus velocity, speed, material, level, mass and id, in id order."""

    name = "frames"

    def begin(self, run: RunContext) -> None:
        self.out = run.out

    def write_frame(self, frame: int, data: FrameData) -> None:
        if data.output_frame:
            write_particles_ply(frame_path(self.out, frame), data.particles.x, data.attributes)
