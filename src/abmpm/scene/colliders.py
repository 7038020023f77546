"""The scene schema of colliders (``[[colliders]]``): the shapes, their contact law
and their motion."""

from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import AfterValidator, Field, Strict, create_model, field_validator, model_validator

from ..geometry.collider_shapes import REGISTRY as SHAPES
from ..geometry.collider_shapes import REQUIRED, ColliderShape, ShapeParameter
from .base import FilePath, Pair, PositiveFloat, Triple, Vec3, _Strict, positive_scale


class Keyframe(_Strict):
    time: float = Field(ge=0, description="s")
    translation: Vec3 = Field((0.0, 0.0, 0.0), description="offset from the rest pose, m")
    rotation: Vec3 = Field((0.0, 0.0, 0.0), description="XYZ Euler angles about the pivot, degrees")


class Motion(_Strict):
    """Kinematic rigid motion of a collider: constant velocities or keyframes."""

    velocity: Vec3 = Field((0.0, 0.0, 0.0), description="m/s")
    angular_velocity: Vec3 = Field((0.0, 0.0, 0.0), description="rad/s about the pivot")
    pivot: Vec3 | None = Field(None, description="rotation centre; default: the collider's center")
    keyframes: Annotated[list[Keyframe], Strict(False)] = Field(
        default_factory=list, description="overrides the velocities"
    )

    @model_validator(mode="after")
    def _sorted(self):
        times = [k.time for k in self.keyframes]
        if any(b <= a for a, b in zip(times, times[1:])):
            raise ValueError("keyframes must have strictly increasing times")
        return self

    @property
    def is_static(self) -> bool:
        return not self.keyframes and not any(self.velocity) and not any(self.angular_velocity)


class _ColliderBase(_Strict):
    name: str = ""
    boundary: Literal["sticky", "slip", "separate"] = "separate"
    friction: float = Field(0.0, ge=0, description="Coulomb friction coefficient")
    separation: float = Field(0.0, ge=0, description="separating speed c of paper Eq. 23, m/s")
    refine: bool = Field(True, description="mark the region around it for refinement (adaptive mode)")
    center: Vec3 = (0.0, 0.0, 0.0)
    rotation: Vec3 = Field((0.0, 0.0, 0.0), description="XYZ Euler angles, degrees")
    motion: Motion = Motion()


class MeshCollider(_ColliderBase):
    shape: Literal["mesh"] = "mesh"
    file: FilePath
    scale: float | Triple = 1.0

    _positive_scale = field_validator("scale")(positive_scale)


def _visible(text: str) -> str:
    if not text.strip():
        raise ValueError("must contain at least one visible character, got only blanks")
    return text


def _field(p: ShapeParameter):
    # the pydantic type and field of a declared shape parameter (collider_shapes.KINDS)
    default = ... if p.default is REQUIRED else p.default
    doc = {"description": p.doc} if p.doc else {}
    if p.kind == "positive":
        return PositiveFloat, Field(default, **doc)
    if p.kind == "non_negative":
        return float, Field(default, ge=0, **doc)
    if p.kind == "pair":
        return Pair, Field(default, **doc)
    if p.kind == "triple":
        return Triple, Field(default, **doc)
    if p.kind == "text":
        return Annotated[str, AfterValidator(_visible)], Field(default, min_length=1, **doc)
    return int | None, Field(default, ge=p.ge, le=p.le, **doc)  # count


def collider_schema(shape: ColliderShape) -> type[_ColliderBase]:
    """The scene schema of a registered collider shape, from its declared parameters:
    ``SheetCollider`` for ``sheet``, with the contact law, pose and motion of every
    collider."""
    fields: dict = {"shape": (Literal[shape.name], shape.name)}
    fields.update({p.name: _field(p) for p in shape.parameters})
    cls_name = "".join(part.capitalize() for part in shape.name.split("_")) + "Collider"
    return create_model(cls_name, __base__=_ColliderBase, __doc__=shape.doc, __module__=__name__, **fields)


# One schema per registered shape (``abmpm.geometry.collider_shapes.REGISTRY``).
SHAPE_SCHEMAS: dict[str, type[_ColliderBase]] = {name: collider_schema(s) for name, s in SHAPES.items()}
SheetCollider = SHAPE_SCHEMAS["sheet"]
ThinBoxCollider = SHAPE_SCHEMAS["thin_box"]
BladeCollider = SHAPE_SCHEMAS["blade"]
CrossedPlatesCollider = SHAPE_SCHEMAS["crossed_plates"]
LetterPanelCollider = SHAPE_SCHEMAS["letter_panel"]
HourglassCollider = SHAPE_SCHEMAS["hourglass"]
FunnelCollider = SHAPE_SCHEMAS["funnel"]
PaddleCollider = SHAPE_SCHEMAS["paddle"]

Collider = Annotated[Union[(MeshCollider, *SHAPE_SCHEMAS.values())], Field(discriminator="shape")]
