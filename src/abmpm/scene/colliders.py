"""The scene schema of colliders (``[[colliders]]``): the shapes, their contact law
and their motion."""

from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import Field, Strict, field_validator, model_validator

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


class SheetCollider(_ColliderBase):
    """Zero-thickness rectangle, normal +y before rotation."""

    shape: Literal["sheet"] = "sheet"
    size: Pair = (1.0, 1.0)
    resolution: int | None = Field(None, ge=1, le=2000, description="quads per side (2 triangles each)")


class ThinBoxCollider(_ColliderBase):
    shape: Literal["thin_box"] = "thin_box"
    size: Triple


class BladeCollider(_ColliderBase):
    """Blade in the xy-plane (normal +z before rotation); thickness 0 is a sheet."""

    shape: Literal["blade"] = "blade"
    length: PositiveFloat
    height: PositiveFloat
    thickness: float = Field(0.0, ge=0)


class CrossedPlatesCollider(_ColliderBase):
    shape: Literal["crossed_plates"] = "crossed_plates"
    size: Pair = (0.4, 0.2)
    thickness: float = Field(0.0, ge=0)


class LetterPanelCollider(_ColliderBase):
    """Panel in the xy-plane with holes shaped like the glyphs of ``text``."""

    shape: Literal["letter_panel"] = "letter_panel"
    text: str = Field("ABC", min_length=1)
    size: Pair = (0.6, 0.3)
    thickness: float = Field(0.0, ge=0)

    @field_validator("text")
    @classmethod
    def _visible(cls, text: str) -> str:
        if not text.strip():
            raise ValueError("must contain at least one visible character, got only blanks")
        return text


class HourglassCollider(_ColliderBase):
    shape: Literal["hourglass"] = "hourglass"
    height: PositiveFloat = 0.6
    radius: PositiveFloat = 0.15
    neck_radius: PositiveFloat = 0.02
    wall_thickness: float = Field(0.0, ge=0)


class FunnelCollider(_ColliderBase):
    shape: Literal["funnel"] = "funnel"
    top_radius: PositiveFloat = 0.2
    pipe_radius: PositiveFloat = 0.03
    cone_height: PositiveFloat = 0.2
    pipe_length: PositiveFloat = 0.1


class PaddleCollider(_ColliderBase):
    shape: Literal["paddle"] = "paddle"
    length: PositiveFloat = 0.3
    height: PositiveFloat = 0.1


Collider = Annotated[
    Union[MeshCollider, SheetCollider, ThinBoxCollider, BladeCollider, CrossedPlatesCollider,
          LetterPanelCollider, HourglassCollider, FunnelCollider, PaddleCollider],
    Field(discriminator="shape"),
]
