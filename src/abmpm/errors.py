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
