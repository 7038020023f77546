"""The writers of a run: one class per kind of output, behind :class:`Writer`
(``begin`` / ``write_frame`` / ``finish``, see :mod:`abmpm.io.writers.base`).

:data:`WRITERS` maps a writer's name to its class, in the order the runner calls
them (the collider mesh of a frame before its particles, the region before the
preview that draws it, the summary last but for the live view, which may keep
serving after the run). :func:`build_writers` picks those the scene's ``[output]``
section asks for. A new kind of output is a module here with a
:class:`Writer` subclass, plus its line in :data:`WRITERS` (and in
:func:`build_writers` if the ``[output]`` section turns it on or off).
"""

from __future__ import annotations

from abmpm.io.writers.base import FrameData, FrameStore, RunContext, Writer
from abmpm.io.writers.beauty import BeautyWriter
from abmpm.io.writers.checkpoints import CheckpointWriter
from abmpm.io.writers.colliders import ColliderMeshWriter
from abmpm.io.writers.frames import ParticleFrameWriter
from abmpm.io.writers.preview import PreviewWriter
from abmpm.io.writers.region import RegionWriter
from abmpm.io.writers.summary import EnergyPlotWriter, SummaryWriter
from abmpm.io.writers.surface import SurfaceWriter
from abmpm.io.writers.usd import UsdWriter
from abmpm.io.writers.viewer import ViewerWriter
from abmpm.scene.model import Output

__all__ = ["WRITERS", "FrameData", "FrameStore", "RunContext", "Writer", "build_writers", "writer_names"]

WRITERS: dict[str, type[Writer]] = {
    "colliders": ColliderMeshWriter,  # colliders/collider_NNNNN.ply
    "frames": ParticleFrameWriter,  # frames/frame_NNNNN.ply
    "surface": SurfaceWriter,  # surfaces/surface_NNNNN_<material>.ply
    "checkpoints": CheckpointWriter,  # checkpoints/checkpoint_NNNNN.npz
    "energy": EnergyPlotWriter,  # energy.png
    "region": RegionWriter,  # region.npz
    "preview": PreviewWriter,  # preview.mp4, preview.png
    "beauty": BeautyWriter,  # beauty.mp4, beauty.png (path-traced surfaces, after the surface writer)
    "usd": UsdWriter,  # particles.usd
    "summary": SummaryWriter,  # summary.json
    "view": ViewerWriter,  # abmpm run --view: live browser view (last: may serve on after the run)
}


def writer_names(output: Output, preview: bool = True, view: bool = False) -> list[str]:
    """Names of the writers that ``output`` (the scene's ``[output]`` section) asks for,
    in :data:`WRITERS` order; ``preview=False`` (``abmpm run --no-preview``) drops the
    preview, ``view=True`` (``abmpm run --view``) adds the live view."""
    wanted = {
        "colliders": output.frames,
        "frames": output.frames,
        "preview": output.preview and preview,
        "usd": output.usd,
        "surface": output.surface,
        "beauty": output.beauty,
        "view": view,
    }
    return [name for name in WRITERS if wanted.get(name, True)]


def build_writers(output: Output, preview: bool = True, view=None) -> list[Writer]:
    """The writers ``output`` asks for, in the order the runner calls them; ``view``
    (True or a :class:`~abmpm.io.writers.viewer.ViewOptions`) adds the live view. A
    writer whose requirements are missing refuses here (AbmpmError), before the run starts."""
    names = writer_names(output, preview, view=bool(view))
    return [WRITERS[name](view) if name == "view" else WRITERS[name]() for name in names]
