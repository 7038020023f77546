"""A zero-thickness plate with round holes along its centre line, normal +y before rotation."""

from ..procedural import perforated_plate
from . import ColliderShape, ShapeParameter

SHAPE = ColliderShape("perforated_plate", perforated_plate, (
    ShapeParameter("size", "pair", (1.0, 1.0), "x and z extent, m"),
    ShapeParameter("hole_diameter", "positive", 0.1, "m"),
    ShapeParameter("holes", "count", 1, "holes, evenly spaced along x", ge=1, le=1000),
), __doc__)
