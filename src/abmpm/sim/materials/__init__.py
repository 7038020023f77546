"""Constitutive models, one module each, registered in :data:`REGISTRY`.

To add a material: write a module that builds a
:class:`~abmpm.sim.materials.base.MaterialModel` named ``MODEL`` (scene parameters,
device fields, wave speed, ``stress`` and ``update`` device functions; see
``elastic.py`` for the shortest one) and add its name to ``MODULES``. Nothing else changes: the scene schema
is generated from the registry, ``MaterialParams`` holds the union of the models'
device fields, and the transfer kernels reach a model only through the dispatch
functions below (unrolled at compile time with ``wp.static`` over the models a
scene uses: :func:`dispatch`).

``model`` ids are positions in ``REGISTRY``.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import warp as wp

from .base import Deformation, MaterialModel, Parameter
from .common import lame
from .fluid import pressure_from_J

wp.set_module_options({"enable_backward": False})

# The registered models: modules of this package, each with a ``MODEL``. Their order
# gives the ids stored in ``MaterialParams.model``.
MODULES = ("fluid", "elastic", "viscoelastic", "sand", "snow")
REGISTRY: tuple[MaterialModel, ...] = tuple(importlib.import_module(f".{name}", __name__).MODEL for name in MODULES)

MODEL_IDS = {m.name: i for i, m in enumerate(REGISTRY)}
BY_NAME = {m.name: m for m in REGISTRY}


def _struct_fields(models) -> dict[str, type]:
    fields: dict[str, type] = {"model": int, "density": float}
    for m in models:
        for name, kind in m.device_fields.items():
            if fields.setdefault(name, kind) is not kind:
                raise TypeError(f"material {m.name!r}: device field {name!r} is {kind}, another model has {fields[name]}")
    return fields


# One row per scene material: the union of every model's device fields (SI units).
MaterialParams = wp.struct(
    type("MaterialParams", (), {"__annotations__": _struct_fields(REGISTRY), "__module__": __name__,
                                "__doc__": "Device parameters of one material (fields of every registered model)."})
)


def material_params(m) -> MaterialParams:
    """A scene material (any object with ``model``, ``density`` and the model's
    parameters as attributes) -> its device row. Fields of other models stay 0."""
    model = BY_NAME[m.model]
    p = MaterialParams()  # every field starts at 0
    p.model = MODEL_IDS[m.model]
    p.density = m.density
    for name, value in model.device_values(m).items():
        setattr(p, name, value)
    return p


def wave_speed(m) -> float:
    """Fastest wave speed of a scene material at rest, m/s: the CFL time step uses it."""
    return BY_NAME[m.model].wave_speed(m)


def kinematic_viscosity(m) -> float:
    """Viscosity over density of a scene material, m^2/s (0 without viscosity): the
    explicit viscous step limit uses it."""
    return getattr(m, "viscosity", 0.0) / m.density


def uses_deformation_gradient(name: str) -> bool:
    """False for models whose F stays the identity and whose J is their ``history``."""
    return BY_NAME[name].uses_F


# --------------------------------------------------------------------------- dispatch


# The models' source, in the names of the functions that dispatch to them. Warp's kernel
# cache keys a kernel by a hash of the code it reaches, but a ``wp.static`` that depends on
# a loop variable (the loops over the models below) is resolved only when the kernel is
# built, after that hash is taken: the model functions it reaches are left out of it, and a
# kernel compiled before an edit of a model (or of ``common.py``) was loaded again after
# it. Found when a new polar decomposition changed nothing measurable: the kernels still
# called the SVD.
_SOURCE_DIGEST = hashlib.sha256(b"".join(p.read_bytes() for p in sorted(Path(__file__).parent.glob("*.py")))
                                ).hexdigest()[:10]


def _dispatching(f, name: str | None = None):
    # a Warp function whose name carries the models' source digest (above)
    f.__qualname__ = f.__name__ = (name or f.__name__) + "_" + _SOURCE_DIGEST
    return wp.func(f)


@_dispatching
def kirchhoff_stress(mat: MaterialParams, F: wp.mat33, C: wp.mat33, history: float):
    """tau = J sigma of the particle's model (used by the force of paper Eq. 9)."""
    for i in range(wp.static(len(REGISTRY))):
        if mat.model == i:
            return wp.static(REGISTRY[i].stress)(mat, F, C, history)
    return wp.mat33(0.0)


@_dispatching
def update_deformation(mat: MaterialParams, F: wp.mat33, C: wp.mat33, history: float, dt: float):
    """F <- (I + dt C) F (paper Eq. 7), then the model's return mapping (Eqs. 13-14)."""
    for i in range(wp.static(len(REGISTRY))):
        if mat.model == i:
            return wp.static(REGISTRY[i].update)(mat, F, C, history, dt)
    out = Deformation()
    out.F = F
    out.history = history
    return out


@_dispatching
def carries_F(mat: MaterialParams):
    """Whether the particle's model keeps a deformation gradient (a solid: its particles
    stay on their F-deformed lattice); False for the models that keep only J."""
    for i in range(wp.static(len(REGISTRY))):
        if wp.static(not REGISTRY[i].uses_F):
            if mat.model == i:
                return False
    return True


@wp.func
def volume_ratio(mat: MaterialParams, F: wp.mat33, history: float):
    """J = V / V0 of a particle: det F, or the ``history`` of models without F."""
    if carries_F(mat):
        return wp.determinant(F)
    return history


@dataclass(frozen=True)
class Dispatch:
    """The per-particle model dispatch of the transfer kernels, over a given set of
    model ids (:func:`dispatch`)."""

    models: tuple[int, ...]
    particle_stress: Any  # wp.func (mat, F array, history array, p, C) -> tau
    deform_particle: Any  # wp.func (mat, F array, history array, p, C, dt), in place
    sound_speed_ratio: Any  # wp.func (mat, history) -> float


ALL_MODELS = tuple(range(len(REGISTRY)))


def _func(f, name: str, models: tuple[int, ...]):
    # one Warp function per model set: a distinct name, or Warp would take the
    # closures of different sets for overloads of one function
    return _dispatching(f, name + "_" + "_".join(map(str, models)))


@functools.cache
def dispatch(models: tuple[int, ...] = ALL_MODELS) -> Dispatch:
    """The dispatch functions reaching only the models ``models`` (sorted ids).

    Why: a kernel that can reach every registered model carries all their code
    (SVDs, return mappings) even where a scene uses one; on Warp's CPU backend that
    alone made the fluid benchmark's P2G a third slower. A scene's transfer kernels
    are compiled for the models it uses; with a single model there is no test at all.
    """
    models = tuple(sorted(models))
    if not models or any(i not in ALL_MODELS for i in models):
        raise ValueError(f"model ids {models}: expected a non-empty subset of {ALL_MODELS}")
    single = len(models) == 1

    def particle_stress(mat: MaterialParams, F: wp.array(dtype=wp.mat33), history: wp.array(dtype=float), p: int,
                        C: wp.mat33):
        # tau of particle p, reading F only for models that use it
        for i in range(wp.static(len(models))):
            if wp.static(single) or mat.model == wp.static(models[i]):
                Fp = wp.identity(n=3, dtype=float)
                if wp.static(REGISTRY[models[i]].uses_F):
                    Fp = F[p]
                return wp.static(REGISTRY[models[i]].stress)(mat, Fp, C, history[p])
        return wp.mat33(0.0)

    def deform_particle(mat: MaterialParams, F: wp.array(dtype=wp.mat33), history: wp.array(dtype=float), p: int,
                        C: wp.mat33, dt: float):
        # update_deformation of particle p in place, touching F only for models that use it
        for i in range(wp.static(len(models))):
            if wp.static(single) or mat.model == wp.static(models[i]):
                Fp = wp.identity(n=3, dtype=float)
                if wp.static(REGISTRY[models[i]].uses_F):
                    Fp = F[p]
                d = wp.static(REGISTRY[models[i]].update)(mat, Fp, C, history[p], dt)
                if wp.static(REGISTRY[models[i]].uses_F):
                    F[p] = d.F
                history[p] = d.history

    def sound_speed_ratio(mat: MaterialParams, history: float):
        # sound speed over the speed at rest (>= 1) of models that stiffen under
        # compression (fluid); 1 for the others
        for i in range(wp.static(len(models))):
            if wp.static(REGISTRY[models[i]].sound_speed_ratio is not None):
                if wp.static(single) or mat.model == wp.static(models[i]):
                    return wp.static(REGISTRY[models[i]].sound_speed_ratio)(mat, history)
        return 1.0

    return Dispatch(models, _func(particle_stress, "particle_stress", models),
                    _func(deform_particle, "deform_particle", models),
                    _func(sound_speed_ratio, "sound_speed_ratio", models))


def model_ids(materials) -> tuple[int, ...]:
    """The sorted model ids of a list of :class:`MaterialParams` rows."""
    return tuple(sorted({int(m.model) for m in materials}))


__all__ = [
    "REGISTRY", "MODEL_IDS", "BY_NAME", "MaterialModel", "Parameter", "MaterialParams", "Deformation",
    "material_params", "wave_speed", "kinematic_viscosity", "uses_deformation_gradient", "lame", "pressure_from_J",
    "kirchhoff_stress", "update_deformation", "Dispatch", "dispatch", "model_ids", "ALL_MODELS",
    "volume_ratio",
]
