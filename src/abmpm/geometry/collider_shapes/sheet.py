"""A zero-thickness rectangle, normal +y before rotation."""

from ..procedural import sheet
from . import ColliderShape, ShapeParameter

SHAPE = ColliderShape("sheet", sheet, (
    ShapeParameter("size", "pair", (1.0, 1.0), "x and z extent, m"),
    ShapeParameter("resolution", "count", None, "quads per side (2 triangles each)", ge=1, le=2000),
), __doc__)
