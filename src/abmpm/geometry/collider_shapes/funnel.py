"""A funnel: a cone on top of a pipe, about y."""

from ..procedural import funnel
from . import ColliderShape, ShapeParameter

SHAPE = ColliderShape("funnel", funnel, (
    ShapeParameter("top_radius", "positive", 0.2, "m"),
    ShapeParameter("pipe_radius", "positive", 0.03, "m"),
    ShapeParameter("cone_height", "positive", 0.2, "m"),
    ShapeParameter("pipe_length", "positive", 0.1, "m"),
), __doc__)
