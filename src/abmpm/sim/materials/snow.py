"""Snow plasticity (Stomakhin et al. 2013): fixed-corotated elasticity that hardens
under compression; ``history`` is the plastic volume ratio J_P."""

from __future__ import annotations

import math
from typing import Any

import warp as wp

from .base import Deformation, MaterialModel, Parameter
from .common import ELASTIC_FIELDS, SOLID_PARAMETERS, fixed_corotated, lame_values, p_wave_speed, trial_deformation

wp.set_module_options({"enable_backward": False})


@wp.func
def stress(mat: Any, F: wp.mat33, C: wp.mat33, J_P: float):
    # hardening: stiffer when compressed (J_P < 1), Stomakhin et al. 2013 Eq. 2
    h = wp.exp(mat.hardening * (1.0 - J_P))
    return fixed_corotated(mat.mu * h, mat.lam * h, F)


@wp.func
def update(mat: Any, F: wp.mat33, C: wp.mat33, J_P: float, dt: float):
    # Eq. 7, then clamp the singular values to [1 - theta_c, 1 + theta_s]; the rest
    # goes to F_P (Eq. 14), whose determinant J_P is kept
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(trial_deformation(F, C, dt), U, sig, V)
    J_old = sig[0] * sig[1] * sig[2]
    for a in range(3):
        sig[a] = wp.clamp(sig[a], 1.0 - mat.theta_c, 1.0 + mat.theta_s)
    J_new = sig[0] * sig[1] * sig[2]
    out = Deformation()
    out.F = U * wp.diag(sig) * wp.transpose(V)
    out.history = J_P * J_old / J_new
    return out


def wave_speed(m) -> float:
    # hardening stiffens compressed snow; allow for J_P down to 1 - 10 theta_c
    return p_wave_speed(m) * math.exp(0.5 * m.hardening * min(1.0, 10.0 * m.critical_compression))


MODEL = MaterialModel(
    name="snow",
    doc="Snow plasticity (Stomakhin et al. 2013).",
    parameters=SOLID_PARAMETERS
    + (
        Parameter("critical_compression", 2.5e-2, "theta_c: singular values below 1 - theta_c are plastic", gt=0.0, lt=1.0),
        Parameter("critical_stretch", 7.5e-3, "theta_s: singular values above 1 + theta_s are plastic", gt=0.0),
        Parameter("hardening", 10.0, "hardening coefficient xi", ge=0.0),
    ),
    device_fields={**ELASTIC_FIELDS, "theta_c": float, "theta_s": float, "hardening": float},
    device_values=lambda m: {
        **lame_values(m),
        "theta_c": m.critical_compression,
        "theta_s": m.critical_stretch,
        "hardening": m.hardening,
    },
    wave_speed=wave_speed,
    stress=stress,
    update=update,
)
