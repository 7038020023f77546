"""An hourglass (a surface of revolution about y) with a narrow neck."""

from ..procedural import hourglass
from . import ColliderShape, ShapeParameter

SHAPE = ColliderShape("hourglass", hourglass, (
    ShapeParameter("height", "positive", 0.6, "m"),
    ShapeParameter("radius", "positive", 0.15, "of the bulbs, m"),
    ShapeParameter("neck_radius", "positive", 0.02, "m"),
    ShapeParameter("wall_thickness", "non_negative", 0.0, "m (0: an open surface)"),
), __doc__)
