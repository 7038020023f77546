"""Two vertical plates crossing at 90 degrees (an X seen from above)."""

from ..procedural import crossed_plates
from . import ColliderShape, ShapeParameter

SHAPE = ColliderShape("crossed_plates", crossed_plates, (
    ShapeParameter("size", "pair", (0.4, 0.2), "width and height of each plate, m"),
    ShapeParameter("thickness", "non_negative", 0.0, "m (0: open sheets)"),
), __doc__)
