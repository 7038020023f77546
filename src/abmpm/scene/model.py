"""The scene description: one validated data model for Python and TOML alike.

A scene built in Python (``Scene(simulation=..., materials=[...], bodies=[...])``)
and a scene loaded from a TOML file go through the same pydantic models, so both
paths get the same defaults and the same error messages. Units are SI throughout
(m, s, kg, Pa); y is up.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, Strict, create_model, field_validator, model_validator

from ..sim.materials import REGISTRY as MATERIAL_MODELS
from ..sim.materials.base import MaterialModel
from ..sim.reconstruct import DEFAULT_SURFACE_THRESHOLD
from .checks import check_feasible

# Types are strict (a string is not a number, 1 is not true) except that an integer is
# a valid float (TOML ``dx = 1``) and containers are lax: a vector may be a TOML list or
# a Python list or tuple, a path a string. The items of a container stay strict.
PositiveFloat = Annotated[float, Field(gt=0)]
Vec3 = Annotated[tuple[float, float, float], Strict(False)]
Pair = Annotated[tuple[PositiveFloat, PositiveFloat], Strict(False)]
Triple = Annotated[tuple[PositiveFloat, PositiveFloat, PositiveFloat], Strict(False)]
FilePath = Annotated[Path, Strict(False)]
Box = Annotated[tuple[Vec3, Vec3], Strict(False)]

# The solver computes in single precision: a number beyond FLOAT32_MAX cannot even be
# stored, and a non-zero one below FLOAT32_TINY loses its precision or becomes 0.
FLOAT32_MAX = 3.4028234663852886e38
FLOAT32_TINY = 1.1754943508222875e-38


def _plain(value):
    """numpy scalars and arrays (np.float32, np.int64, np.bool_) -> Python numbers and
    lists, recursively, so that strict validation treats them like the Python values."""
    if isinstance(value, (list, tuple)):
        out = [_plain(v) for v in value]
        return tuple(out) if isinstance(value, tuple) else out
    if type(value).__module__ == "numpy" and hasattr(value, "tolist"):
        return value.tolist()
    return value


def _out_of_range(value, index: tuple = ()):
    """(index, value) of the first float in ``value`` that float32 cannot hold, or None."""
    if isinstance(value, float) and (abs(value) > FLOAT32_MAX or 0.0 < abs(value) < FLOAT32_TINY):
        return index, value
    if isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            found = _out_of_range(v, index + (i,))
            if found is not None:
                return found
    return None


class _Strict(BaseModel):
    # Unknown keys are errors: a typo in a scene file must not be silently ignored.
    # strict: "0.04" is not a number and "yes" is not a boolean; allow_inf_nan: inf and
    # nan (valid TOML) are refused wherever a number is expected, vectors included.
    model_config = ConfigDict(extra="forbid", validate_assignment=True, strict=True, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _numpy_scalars(cls, data):
        return {k: _plain(v) for k, v in data.items()} if isinstance(data, dict) else data

    @field_validator("*", mode="after")
    @classmethod
    def _single_precision(cls, value):
        found = _out_of_range(value)
        if found is not None:
            index, x = found
            item = f" (item {''.join(f'[{i}]' for i in index)})" if index else ""
            raise ValueError(
                f"{x:g}{item} is outside the single-precision range of the solver "
                "(0 or 1.2e-38 <= |x| <= 3.4e38)"
            )
        return value


# --------------------------------------------------------------------------- simulation


WallType = Literal["sticky", "slip", "separate"]


class WallFace(_Strict):
    type: WallType | None = None
    friction: float | None = Field(None, ge=0)


class Walls(_Strict):
    """Boundary condition on the six faces of the domain box.

    ``type`` and ``friction`` apply to every face; a face table (``x_min`` ...
    ``z_max``) overrides them for that face, e.g. a rough floor (``y_min``) in a
    tank with slippery side walls.
    """

    type: WallType = "separate"
    friction: float = Field(0.0, ge=0, description="Coulomb friction coefficient (slip/separate walls)")
    x_min: WallFace | None = None
    x_max: WallFace | None = None
    y_min: WallFace | None = None
    y_max: WallFace | None = None
    z_min: WallFace | None = None
    z_max: WallFace | None = None

    def face(self, name: str) -> tuple[str, float]:
        """(type, friction) in force on one face."""
        f = getattr(self, name) or WallFace()
        return (f.type or self.type, self.friction if f.friction is None else f.friction)


class Refinement(_Strict):
    """Adaptive boundary refinement (paper Sections 3.2, 4.2, 5.2)."""

    mode: Literal["original", "adaptive", "finest"] = Field(
        "original", description="original: coarse grid only; adaptive: refine near boundaries; finest: all fine"
    )
    factor: int = Field(2, ge=2, le=4, description="b: the fine grid spacing is dx / b")
    criterion: Literal["feature", "density", "both"] = Field(
        "feature",
        description="feature: refine around free space narrower than gap_cells and around moving edges; "
        "density: the paper's boundary density alone (refines whole sheets); both: their union",
    )
    gap_cells: float = Field(3.0, gt=0, description="feature criterion: gaps narrower than this (coarse cells) are refined")
    threshold: float = Field(1.5, gt=0, description="boundary density above which coarse cells are refined")
    bandwidth: float = Field(1.0, gt=0, description="Gaussian bandwidth h of the density, in coarse cells")
    halo: int = Field(1, ge=0, description="refined cells grow by this many coarse cells")
    boxes: Annotated[list[Box], Strict(False)] = Field(
        default_factory=list, description="extra boxes to refine, [min, max]"
    )
    merge: bool = Field(True, description="merge split families back once they have left the region")
    merge_margin: int = Field(1, ge=0, description="hysteresis: coarse cells beyond the region before a merge")
    reconstruct: bool = Field(
        True, description="surface particle reconstruction after a split (paper Section 4.3); false: plain split"
    )
    surface_threshold: float = Field(
        DEFAULT_SURFACE_THRESHOLD, gt=0, description="t_p of Eq. 16 in units of (mass of a full coarse cell) / dx"
    )

    @field_validator("boxes")
    @classmethod
    def _ordered_boxes(cls, boxes):
        for i, (lo, hi) in enumerate(boxes):
            bad = [a for a in range(3) if lo[a] > hi[a]]
            if bad:
                a = bad[0]
                raise ValueError(
                    f"box {i}: min must not exceed max on any axis (axis {'xyz'[a]}: {lo[a]:g} > {hi[a]:g})"
                )
        return boxes

    @property
    def split_count(self) -> int:
        """N_s = b^3 children per split particle."""
        return self.factor**3


class SimulationSettings(_Strict):
    domain_min: Vec3 = (0.0, 0.0, 0.0)
    domain_max: Vec3 = (1.0, 1.0, 1.0)
    dx: PositiveFloat = 0.02
    gravity: Vec3 = (0.0, -9.81, 0.0)
    duration: PositiveFloat = 2.0
    fps: PositiveFloat = 30.0
    cfl: float = Field(0.4, gt=0, le=1.0, description="time step = cfl * dx / wave speed")
    max_dt: PositiveFloat = 1e-3
    seed: int = Field(0, ge=0, description="seed of the particle jitter")
    device: str | None = Field(None, description="'cpu', 'cuda' or 'cuda:N'; default: cuda when available")
    walls: Walls = Walls()
    refinement: Refinement = Refinement()
    cpic: bool = Field(
        True, description="compatible transfers at colliders; false: plain grid boundary (leaks through thin sheets)"
    )
    cuda_graph: bool = Field(
        False, description="replay the substeps between host points as captured CUDA graphs (CUDA only; experimental)"
    )

    @model_validator(mode="after")
    def _domain_is_a_box(self):
        for axis in range(3):
            if not self.domain_max[axis] > self.domain_min[axis]:
                raise ValueError(
                    f"domain_max must exceed domain_min on every axis (axis {'xyz'[axis]}: "
                    f"{self.domain_min[axis]} >= {self.domain_max[axis]})"
                )
        far = max(max(abs(c) for c in self.domain_min), max(abs(c) for c in self.domain_max))
        if far / self.dx > 2**20:
            key = "domain_min" if max(abs(c) for c in self.domain_min) >= far else "domain_max"
            raise ValueError(
                f"{key} lies {far:g} m from the origin, {far / self.dx:.3g} cells of dx: "
                "single precision cannot resolve the grid there (at most 2^20 = 1048576 cells); "
                "move the domain near the origin or raise dx"
            )
        cells = [(self.domain_max[a] - self.domain_min[a]) / self.dx for a in range(3)]
        if min(cells) < 4:
            raise ValueError(f"dx={self.dx} leaves fewer than 4 cells across the domain")
        if math.prod(c + 8 for c in cells) > 2.0e9:
            raise ValueError(f"dx={self.dx} makes a grid of more than 2e9 nodes")
        return self


# --------------------------------------------------------------------------- materials


class _MaterialBase(_Strict):
    name: str = Field(min_length=1)
    density: PositiveFloat = 1000.0


def _material_schema(model: MaterialModel) -> type[_MaterialBase]:
    """The scene schema of a registered material model, from its declared parameters."""
    fields: dict = {"model": (Literal[model.name], model.name)}
    for prm in model.parameters:
        bounds = {k: getattr(prm, k) for k in ("gt", "ge", "lt", "le") if getattr(prm, k) is not None}
        fields[prm.name] = (float, Field(prm.default, description=prm.doc, **bounds))
    cls_name = "".join(part.capitalize() for part in model.name.split("_"))
    return create_model(cls_name, __base__=_MaterialBase, __doc__=model.doc, __module__=__name__, **fields)


# One schema per registered material model (``abmpm.sim.materials.REGISTRY``).
MATERIAL_SCHEMAS: dict[str, type[_MaterialBase]] = {m.name: _material_schema(m) for m in MATERIAL_MODELS}
Fluid = MATERIAL_SCHEMAS["fluid"]
Elastic = MATERIAL_SCHEMAS["elastic"]
Viscoelastic = MATERIAL_SCHEMAS["viscoelastic"]
Sand = MATERIAL_SCHEMAS["sand"]
Snow = MATERIAL_SCHEMAS["snow"]

Material = Annotated[Union[tuple(MATERIAL_SCHEMAS.values())], Field(discriminator="model")]


# --------------------------------------------------------------------------- bodies


class _BodyBase(_Strict):
    material: str = Field(min_length=1, description="name of a material of this scene")
    velocity: Vec3 = (0.0, 0.0, 0.0)
    angular_velocity: Vec3 = Field((0.0, 0.0, 0.0), description="rad/s, about the body's centre")
    particles_per_cell: int = Field(8, ge=1, le=125)

    @field_validator("particles_per_cell")
    @classmethod
    def _cube_number(cls, n: int) -> int:
        k = round(n ** (1 / 3))
        if k**3 != n:
            raise ValueError(f"must be a cube number (1, 8, 27, 64, 125), got {n}")
        return n


class BoxBody(_BodyBase):
    shape: Literal["box"] = "box"
    min: Vec3
    max: Vec3

    @model_validator(mode="after")
    def _ordered(self):
        if any(self.max[a] <= self.min[a] for a in range(3)):
            raise ValueError("box max must exceed min on every axis")
        return self


class SphereBody(_BodyBase):
    shape: Literal["sphere"] = "sphere"
    center: Vec3
    radius: PositiveFloat


class EllipsoidBody(_BodyBase):
    shape: Literal["ellipsoid"] = "ellipsoid"
    center: Vec3
    radii: Triple
    rotation: Vec3 = Field((0.0, 0.0, 0.0), description="XYZ Euler angles, degrees")


class MeshBody(_BodyBase):
    shape: Literal["mesh"] = "mesh"
    file: FilePath
    scale: float | Triple = 1.0
    rotation: Vec3 = (0.0, 0.0, 0.0)
    translation: Vec3 = (0.0, 0.0, 0.0)

    @field_validator("scale")
    @classmethod
    def _positive_scale(cls, s):
        if isinstance(s, (int, float)) and s <= 0:
            raise ValueError("must be > 0")
        return s


class BunnyBody(_BodyBase):
    """Procedural bunny-like shape (a union of ellipsoids) for demos."""

    shape: Literal["bunny"] = "bunny"
    center: Vec3
    size: PositiveFloat = Field(0.2, description="overall height of the bunny, m")
    rotation: Vec3 = (0.0, 0.0, 0.0)


Body = Annotated[
    Union[BoxBody, SphereBody, EllipsoidBody, MeshBody, BunnyBody], Field(discriminator="shape")
]


# --------------------------------------------------------------------------- colliders


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

    _positive_scale = field_validator("scale")(MeshBody._positive_scale.__func__)


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


# --------------------------------------------------------------------------- output


class SurfaceMeshOptions(_Strict):
    """``[output.surface_mesh]``: how the surface meshes are built (splashsurf). Lengths
    are relative to the particle spacing s (the cube root of a particle's volume)."""

    radius: float = Field(0.5, gt=0.0, le=4.0, description="particle radius, in particle spacings")
    fluid_smoothing_length: float = Field(
        3.0, ge=1.0, le=8.0, description="SPH kernel smoothing length for fluids, in particle radii"
    )
    solid_smoothing_length: float = Field(
        2.0, ge=1.0, le=8.0, description="SPH kernel smoothing length for solids, in particle radii"
    )
    cube_size: float = Field(1.0, ge=0.25, le=4.0, description="marching-cubes cell, in particle radii")
    iso: float = Field(0.6, gt=0.0, lt=2.0, description="level of the SPH volume fraction where the surface is")
    fluid_smoothing_iters: int = Field(10, ge=0, le=500, description="weighted Laplacian smoothing of fluid surfaces")
    solid_smoothing_iters: int = Field(0, ge=0, le=500, description="smoothing of solid surfaces (0 keeps edges sharp)")


class Output(_Strict):
    frames: bool = True
    frame_every: int = Field(1, ge=1, description="write every N-th frame")
    preview: bool = True
    color_by: Literal["auto", "material", "speed", "level"] = Field(
        "auto", description="auto: by level in adaptive mode (blue original, white subdivided), else by material"
    )
    checkpoint_every: int = Field(10, ge=1, description="write a checkpoint every N frames")
    usd: bool = False
    surface: bool = Field(False, description="write surfaces/surface_NNNNN_<material>.ply (needs pysplashsurf)")
    surface_mesh: SurfaceMeshOptions = SurfaceMeshOptions()
    beauty: bool = Field(False, description="path-trace beauty.mp4 / beauty.png of the surfaces at the end (needs mitsuba)")
    beauty_colliders: Literal["metal", "glass"] = Field("metal", description="the colliders' look in the beauty pass")


# --------------------------------------------------------------------------- scene


def with_mode(scene: "Scene", mode: str) -> "Scene":
    """The same scene run in another refinement mode (original, adaptive, finest)."""
    st = scene.simulation
    refinement = st.refinement.model_copy(update={"mode": mode})
    return scene.model_copy(update={"simulation": st.model_copy(update={"refinement": refinement})})


class Scene(_Strict):
    name: str = "scene"
    description: str = Field("", description="one line shown by `abmpm scenes`")
    simulation: SimulationSettings = SimulationSettings()
    materials: Annotated[list[Material], Strict(False)] = Field(min_length=1)
    bodies: Annotated[list[Body], Strict(False)] = Field(min_length=1)
    colliders: Annotated[list[Collider], Strict(False)] = Field(default_factory=list)
    output: Output = Output()
    # Folder that relative paths (mesh files) resolve against; set by the TOML loader.
    base_dir: FilePath | None = Field(None, exclude=True)

    @model_validator(mode="after")
    def _references(self):
        names = [m.name for m in self.materials]
        for i, n in enumerate(names):
            if n in names[:i]:
                raise ValueError(f"materials[{i}].name: duplicate material name {n!r}")
        for i, b in enumerate(self.bodies):
            if b.material not in names:
                raise ValueError(
                    f"bodies[{i}].material: unknown material {b.material!r} (known: {', '.join(names)})"
                )
        return self

    def check_feasible(self, mode: str | None = None, device: str | None = None) -> None:
        """Refuse (SceneError naming the key) a scene that cannot run: its grid or
        particles do not fit in memory, or it cannot be time-stepped. See
        :mod:`abmpm.scene.checks`; nothing is allocated."""
        check_feasible(self, mode, device)

    def material_index(self, name: str) -> int:
        return [m.name for m in self.materials].index(name)

    def resolve(self, path: Path) -> Path:
        path = Path(path).expanduser()
        if not path.is_absolute() and self.base_dir is not None:
            path = Path(self.base_dir) / path
        return path
