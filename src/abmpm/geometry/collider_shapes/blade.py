"""A blade in the xy-plane (normal +z before rotation); thickness 0 is a sheet."""

from ..procedural import blade
from . import ColliderShape, ShapeParameter

SHAPE = ColliderShape("blade", blade, (
    ShapeParameter("length", "positive", doc="m, along x"),
    ShapeParameter("height", "positive", doc="m, along y"),
    ShapeParameter("thickness", "non_negative", 0.0, "m, along z (0: an open sheet)"),
), __doc__)
