"""Weakly compressible fluid: Tait equation of state plus Newtonian viscosity.

A fluid keeps no shear memory, only its volume ratio J, which lives in the
particle's ``history`` (its F stays the identity): no SVD and no F traffic.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import warp as wp

from .base import Deformation, MaterialModel, Parameter
from .common import viscous_kirchhoff

wp.set_module_options({"enable_backward": False})


def pressure_from_J(bulk: float | np.ndarray, gamma: float, J):
    """Tait pressure K (J^-gamma - 1) / gamma (host side, for diagnostics and tests)."""
    return bulk * (np.power(J, -gamma) - 1.0) / gamma


@wp.func
def tait_power(mat: Any, J: float):
    # J^-gamma. Integer exponents (the usual 1 or 7) by multiplication: pow() would
    # cost as much as a third of the whole P2G on the CPU.
    n = int(mat.gamma)
    inv_J = 1.0 / J
    r = float(1.0)
    if float(n) == mat.gamma:
        for _ in range(n):
            r = r * inv_J
    else:
        r = wp.pow(J, -mat.gamma)
    return r


@wp.func
def fluid_pressure(mat: Any, J: float):
    # Tait equation of state p = K (J^-gamma - 1) / gamma, so dp/dJ = -K at J = 1.
    return mat.bulk * (tait_power(mat, J) - 1.0) / mat.gamma


@wp.func
def stress(mat: Any, F: wp.mat33, C: wp.mat33, J: float):
    # tau = -p J I + viscous part
    return wp.identity(n=3, dtype=float) * (-fluid_pressure(mat, J) * J) + viscous_kirchhoff(mat.viscosity, J, C)


@wp.func
def update(mat: Any, F: wp.mat33, C: wp.mat33, J: float, dt: float):
    # J <- det(I + dt C) J: the determinant of Eq. 7
    out = Deformation()
    out.F = F
    out.history = wp.determinant(wp.identity(n=3, dtype=float) + dt * C) * J
    return out


@wp.func
def sound_speed_ratio(mat: Any, J: float):
    """Sound speed of a fluid compressed to J over its speed at rest: dp/drho =
    K J^(1 - gamma) / rho0, so sqrt(J^(1 - gamma)), > 1 under compression. An impact
    compresses the fluid and its sound speed grows with it; the CFL step must follow
    (host ``wave_speed`` is the speed at rest). Expanded fluid: 1."""
    if J >= 1.0 or J <= 0.0:
        return 1.0
    return wp.sqrt(J * tait_power(mat, J))


MODEL = MaterialModel(
    name="fluid",
    doc="Weakly compressible fluid: p = K (1/J^gamma - 1)/gamma plus Newtonian viscosity.",
    parameters=(
        Parameter("bulk_modulus", 2.0e5, "bulk modulus K, Pa", gt=0.0),
        Parameter("gamma", 7.0, "Tait exponent of the equation of state (water: 7)", ge=1.0, le=100.0),
        Parameter("viscosity", 0.0, "dynamic viscosity, Pa s", ge=0.0),
    ),
    device_fields={"bulk": float, "gamma": float, "viscosity": float},
    device_values=lambda m: {"bulk": m.bulk_modulus, "gamma": m.gamma, "viscosity": m.viscosity},
    wave_speed=lambda m: math.sqrt(m.bulk_modulus / m.density),
    stress=stress,
    update=update,
    uses_F=False,
    sound_speed_ratio=sound_speed_ratio,
)
