"""What a material module declares: :class:`MaterialModel`.

A material is one module in this package that builds a :class:`MaterialModel` and is
listed once in ``REGISTRY`` (``__init__.py``). The model carries

* its **scene parameters** (:class:`Parameter`: name, default, bounds, unit): the
  scene schema is generated from them, so a scene file can use the material at once;
* its **device fields** and how they are computed from the scene parameters (SI
  units): the fields of every registered model together make the
  ``MaterialParams`` struct that kernels receive;
* its **wave speed** (host side, for the CFL time step);
* its **device functions**: the Kirchhoff stress tau = J sigma used by the MLS-MPM
  force (paper Eq. 9) and the deformation update (Eq. 7 followed by the model's
  return mapping, Eqs. 13-14). Both take the material row as their first argument
  (typed ``Any``: Warp specialises them for ``MaterialParams``), so a module never
  imports the struct that its own fields help to build.

Every particle has one scalar ``history`` beside F whose meaning belongs to the
model (fluid: volume ratio J; snow: plastic J_P; sand: accumulated volume
correction; elastic: unused, stays 1).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import warp as wp


@dataclass(frozen=True)
class Parameter:
    """One scene parameter of a material (a float), with the bounds the scene checks."""

    name: str
    default: float
    doc: str = ""
    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None


@dataclass(frozen=True)
class MaterialModel:
    name: str  # the scene's ``model = "..."``
    doc: str  # one line for the scene schema and docs
    parameters: tuple[Parameter, ...]  # scene parameters besides name and density
    device_fields: dict[str, type]  # fields this model reads from MaterialParams
    device_values: Callable[[Any], dict[str, float]]  # scene material -> device field values
    wave_speed: Callable[[Any], float]  # scene material -> fastest wave speed at rest, m/s
    stress: Any  # wp.func (mat, F, C, history) -> Kirchhoff stress tau (mat33)
    update: Any  # wp.func (mat, F, C, history, dt) -> Deformation (F, history)
    uses_F: bool = True  # False: F stays the identity and J lives in ``history`` (no F traffic)
    # wp.func (mat, history) -> sound speed over the speed at rest (>= 1), for models
    # whose stiffness grows under compression faster than ``wave_speed`` allows
    sound_speed_ratio: Any = None
    extra: dict = field(default_factory=dict)


@wp.struct
class Deformation:
    """Result of a deformation update: the new F and the new scalar history."""

    F: wp.mat33
    history: float
