"""A closed box, for plates of a given thickness."""

from ..procedural import thin_box
from . import ColliderShape, ShapeParameter

SHAPE = ColliderShape("thin_box", thin_box, (ShapeParameter("size", "triple", doc="x, y and z extent, m"),), __doc__)
