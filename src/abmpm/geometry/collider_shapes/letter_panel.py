"""A panel in the xy-plane with holes shaped like the glyphs of ``text``."""

from ..procedural import letter_panel
from . import ColliderShape, ShapeParameter

SHAPE = ColliderShape("letter_panel", letter_panel, (
    ShapeParameter("text", "text", "ABC", "the letters cut out of the panel"),
    ShapeParameter("size", "pair", (0.6, 0.3), "width and height, m"),
    ShapeParameter("thickness", "non_negative", 0.0, "m (0: an open sheet)"),
), __doc__)
