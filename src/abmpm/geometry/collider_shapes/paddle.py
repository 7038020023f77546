"""A flat paddle (a blade turning about its own middle), normal +z before rotation."""

from ..procedural import paddle
from . import ColliderShape, ShapeParameter

SHAPE = ColliderShape("paddle", paddle, (
    ShapeParameter("length", "positive", 0.3, "m, along x"),
    ShapeParameter("height", "positive", 0.1, "m, along y"),
), __doc__)
