"""User-facing errors.

Everything a user can get wrong (a scene key, a mesh file, an output folder) raises
an :class:`AbmpmError` subclass whose message names the file and the field. The CLI
prints that message on one line and exits non-zero, without a traceback.
"""


class AbmpmError(Exception):
    """Base class of errors caused by user input rather than by a bug."""


class SceneError(AbmpmError):
    """A scene description is invalid (message names the file and the key)."""


class MeshError(AbmpmError):
    """A mesh file is missing, unreadable or unsuitable (message names the file)."""


class OutputError(AbmpmError):
    """The output folder cannot be written."""


class SimulationBlowUp(AbmpmError):
    """The state became non-finite or violated the CFL bound; the run stops."""


class OutOfMemory(AbmpmError):
    """An allocation failed during a run (adaptive mode's split children, a finer grid)."""


def allocation_failure(exc: BaseException) -> bool:
    """Whether ``exc`` is a failed allocation: Python's MemoryError or Warp's RuntimeError
    ("Failed to allocate N bytes on device ...")."""
    return isinstance(exc, MemoryError) or (isinstance(exc, RuntimeError) and "Failed to allocate" in str(exc))


OUT_OF_MEMORY_HINT = ("raise simulation.dx, lower simulation.refinement.factor (adaptive mode splits each particle "
                      "of the refined region into factor^3) or shrink the refined region or the bodies")
