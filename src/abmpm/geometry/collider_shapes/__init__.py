"""Collider shapes, one module each, registered in :data:`REGISTRY`.

To add a shape: write a module here that defines ``SHAPE``, a
:class:`ColliderShape` (its scene name, a builder returning a
:class:`trimesh.Trimesh` in its own frame around the origin, and the parameters a
scene file sets, each a :class:`ShapeParameter`), and add its name to ``MODULES``.
Nothing else changes: the scene schema (``[[colliders]] shape = "..."``, its
validation and error messages) is generated from the declared parameters
(``abmpm.scene.colliders``), and the placement passes exactly those parameters to
the builder, by name (``abmpm.geometry.placement``). ``tests/test_toy_shape.py``
adds one this way.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

REQUIRED = object()  # a parameter without a default: the scene must set it

# what a parameter holds, and what the scene schema checks for it
KINDS = {
    "positive": "a number > 0",
    "non_negative": "a number >= 0",
    "pair": "two numbers > 0",
    "triple": "three numbers > 0",
    "text": "a string with at least one visible character",
    "count": "a whole number in [ge, le], or none",
}


@dataclass(frozen=True)
class ShapeParameter:
    name: str  # the builder's keyword and the scene file's key
    kind: str  # one of KINDS
    default: Any = REQUIRED
    doc: str = ""
    ge: int | None = None  # "count": bounds
    le: int | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"shape parameter {self.name!r}: kind {self.kind!r} is not one of {sorted(KINDS)}")


@dataclass(frozen=True)
class ColliderShape:
    name: str  # ``shape = "<name>"`` in a scene file
    build: Callable[..., Any]  # build(**parameters) -> trimesh.Trimesh around the origin
    parameters: tuple[ShapeParameter, ...] = ()
    doc: str = ""

    def arguments(self, collider) -> dict:
        """The builder's keyword arguments from a scene collider: every declared parameter."""
        return {p.name: getattr(collider, p.name) for p in self.parameters}


# The registered shapes: modules of this package, each with a ``SHAPE``.
MODULES = ("sheet", "thin_box", "blade", "crossed_plates", "letter_panel", "hourglass", "funnel", "paddle", "perforated_plate")
REGISTRY: dict[str, ColliderShape] = {
    s.name: s for s in (importlib.import_module(f".{m}", __name__).SHAPE for m in MODULES)
}
