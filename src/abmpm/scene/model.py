"""The scene description: one validated data model for Python and TOML alike.

A scene built in Python (``Scene(simulation=..., materials=[...], bodies=[...])``)
and a scene loaded from a TOML file go through the same pydantic models, so both
paths get the same defaults and the same error messages. Units are SI throughout
(m, s, kg, Pa); y is up.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Annotated, Literal, Union

from pydantic import Field, Strict, create_model, field_validator, model_validator

from ..runtime import device_name_problem
from ..sim.materials import REGISTRY as MATERIAL_MODELS
from ..sim.materials.base import MaterialModel
from ..sim.reconstruct import DEFAULT_SURFACE_THRESHOLD
from .base import Box, FilePath, PositiveFloat, Triple, Vec3, _Strict, positive_scale
from .checks import check_feasible
from .colliders import (  # noqa: F401 (the collider schema, re-exported: abmpm.scene.model is the scene's one namespace)
    BladeCollider,
    Collider,
    CrossedPlatesCollider,
    FunnelCollider,
    HourglassCollider,
    Keyframe,
    LetterPanelCollider,
    MeshCollider,
    Motion,
    PaddleCollider,
    SheetCollider,
    ThinBoxCollider,
)

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
    images: bool = Field(
        False, description="particles near a wall add their mirror images' stress, so the wall holds up the first "
        "layers as the bulk does (a tank at rest 4-5 times quieter; docs/method.md, 'Wall images'); experimental"
    )
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
    bandwidth: float = Field(1.0, gt=0, le=16, description="Gaussian bandwidth h of the density, in coarse cells "
                             "(its kernel spans 3 h each way: up to 16)")
    halo: int = Field(1, ge=0, description="refined cells grow by this many coarse cells")
    boxes: Annotated[list[Box], Strict(False)] = Field(
        default_factory=list, description="extra boxes to refine, [min, max]"
    )
    merge: bool = Field(True, description="merge split families back once they have left the region")
    merge_strays: bool = Field(
        True, description="with merge: also merge a fluid's children whose families tore apart, b^3 at a time where "
        "one cell of the parent lattice holds at least b^3 of them"
    )
    time_steps: Literal["global", "per_level"] = Field(
        "per_level", description="per_level: level-0 particles far from the fine level take the coarse time step; "
        "global: every particle takes the finest step"
    )
    coupling: Literal["overlap", "partition"] = Field(
        "overlap", description="overlap: the paper's Eq. 8 (each level scatters to both grids, gathers from its "
        "own); partition: one partition of unity over both grids' functions, momentum exact, one time step for "
        "all (experimental; docs/method.md, 'The two grids as one basis')"
    )
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
    stiffening: Literal["particle", "node"] = Field(
        "particle", description="CFL signal of compressed fluid: particle: the most compressed particle's sound "
        "speed; node: a bound of the grid's fastest mode, which one compressed particle among others raises less "
        "(fewer steps; docs/method.md, 'Time step')"
    )
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
    def _partition_without_images(self):
        if self.refinement.coupling == "partition" and self.walls.images:
            raise ValueError("refinement.coupling = 'partition' does not add the walls' images yet: set walls.images "
                             "= false or coupling = 'overlap'")
        return self

    @field_validator("device")
    @classmethod
    def _device_name(cls, device: str | None) -> str | None:
        # whether this machine has it is known only when the run starts (choose_device)
        problem = None if device is None else device_name_problem(device)
        if problem:
            raise ValueError(problem)
        return device

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
        for i, (lo, hi) in enumerate(self.refinement.boxes):
            out = [a for a in range(3) if hi[a] <= self.domain_min[a] or lo[a] >= self.domain_max[a]]
            if out:
                a = out[0]
                raise ValueError(
                    f"refinement.boxes[{i}]: the box lies outside the domain on axis {'xyz'[a]} ({lo[a]:g} to "
                    f"{hi[a]:g}, domain {self.domain_min[a]:g} to {self.domain_max[a]:g}): it would refine nothing"
                )
            # a cell is refined when its centre lies in the box (geometry/region.py)
            for a in range(3):
                first = math.ceil((lo[a] - self.domain_min[a]) / self.dx - 0.5)
                if self.domain_min[a] + (first + 0.5) * self.dx > hi[a]:
                    raise ValueError(
                        f"refinement.boxes[{i}]: the box holds no cell centre on axis {'xyz'[a]} ({lo[a]:g} to "
                        f"{hi[a]:g}; cells are dx = {self.dx:g} wide and a cell is refined when its centre is in "
                        "the box): it would refine nothing"
                    )
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

    _positive_scale = field_validator("scale")(positive_scale)


class BunnyBody(_BodyBase):
    """Procedural bunny-like shape (a union of ellipsoids) for demos."""

    shape: Literal["bunny"] = "bunny"
    center: Vec3
    size: PositiveFloat = Field(0.2, description="overall height of the bunny, m")
    rotation: Vec3 = (0.0, 0.0, 0.0)


Body = Annotated[
    Union[BoxBody, SphereBody, EllipsoidBody, MeshBody, BunnyBody], Field(discriminator="shape")
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
    keep_checkpoints: int | None = Field(
        None, ge=1, description="keep only the newest N checkpoints, removing older ones as new ones are written "
        "(default: keep all; --resume needs only the newest)"
    )
    usd: bool = False
    surface: bool = Field(False, description="write surfaces/surface_NNNNN_<material>.ply (needs pysplashsurf)")
    surface_mesh: SurfaceMeshOptions = SurfaceMeshOptions()
    beauty: bool = Field(False, description="path-trace beauty.mp4 / beauty.png of the surfaces at the end (needs mitsuba)")
    beauty_colliders: Literal["metal", "glass"] = Field("metal", description="the colliders' look in the beauty pass")


# --------------------------------------------------------------------------- scene


def with_mode(scene: "Scene", mode: str, **refinement_settings) -> "Scene":
    """The same scene run in another refinement mode (original, adaptive, finest), with
    other ``[simulation.refinement]`` settings too if given (``factor=3``)."""
    st = scene.simulation
    refinement = st.refinement.model_copy(update={"mode": mode, **refinement_settings})
    return scene.model_copy(update={"simulation": st.model_copy(update={"refinement": refinement})})


# a scene's name is its default output folder (out/<name>/), so it is one plain folder name
SCENE_NAME = re.compile(r"[^./\\\x00\s][^/\\\x00]*")


class Scene(_Strict):
    name: str = Field("scene", description="the default output folder is out/<name>/: one folder name, with no / "
                                           "or \\, not starting with a dot or a space")
    description: str = Field("", description="one line shown by `abmpm scenes`")
    simulation: SimulationSettings = SimulationSettings()
    materials: Annotated[list[Material], Strict(False)] = Field(min_length=1)
    bodies: Annotated[list[Body], Strict(False)] = Field(min_length=1)
    colliders: Annotated[list[Collider], Strict(False)] = Field(default_factory=list)
    output: Output = Output()
    # Folder that relative paths (mesh files) resolve against; set by the TOML loader.
    base_dir: FilePath | None = Field(None, exclude=True)

    @field_validator("name")
    @classmethod
    def _folder_name(cls, name: str) -> str:
        if not SCENE_NAME.fullmatch(name):
            raise ValueError(f"{name!r} is not a plain folder name (it names the output folder out/<name>/): "
                             "no / or \\, not empty, not starting with a dot or a space")
        return name

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
