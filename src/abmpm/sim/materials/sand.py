"""Drucker-Prager elastoplastic sand (Klar et al. 2016), cohesionless.

Elasticity is St. Venant-Kirchhoff in Hencky strain; ``history`` accumulates the
volume correction of the projections to the cone tip.
"""

from __future__ import annotations

import math
from typing import Any

import warp as wp

from .base import Deformation, MaterialModel, Parameter
from .common import (
    ELASTIC_FIELDS,
    SOLID_PARAMETERS,
    from_hencky,
    hencky,
    hencky_kirchhoff,
    lame_values,
    p_wave_speed,
    trial_deformation,
)

wp.set_module_options({"enable_backward": False})


def cone_coefficient(friction_angle_deg: float) -> float:
    # alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi))  (Klar et al. 2016, Eq. 27)
    s = math.sin(math.radians(friction_angle_deg))
    return math.sqrt(2.0 / 3.0) * 2.0 * s / (3.0 - s)


@wp.func
def stress(mat: Any, F: wp.mat33, C: wp.mat33, history: float):
    return hencky_kirchhoff(mat.mu, mat.lam, F)


@wp.func
def update(mat: Any, F: wp.mat33, C: wp.mat33, history: float, dt: float):
    # Eq. 7, then the Drucker-Prager projection in Hencky strain (Klar et al. 2016,
    # Section 7.3.1)
    F_trial = trial_deformation(F, C, dt)
    h = hencky(F_trial)
    eps = h.eps
    tr = eps[0] + eps[1] + eps[2]
    out = Deformation()
    out.F = F_trial
    out.history = history
    if tr >= 0.0:
        # expansion: cohesionless sand carries no tension, project to the cone tip
        out.F = h.U * wp.transpose(h.V)
        out.history = history + tr
        return out
    dev = eps - wp.vec3(tr / 3.0)
    dev_norm = wp.length(dev)
    dgamma = dev_norm + (3.0 * mat.lam + 2.0 * mat.mu) / (2.0 * mat.mu) * tr * mat.sand_alpha
    if dgamma <= 0.0 or dev_norm < 1.0e-12:
        return out  # inside the yield cone
    out.F = from_hencky(h, eps - (dgamma / dev_norm) * dev)
    return out


MODEL = MaterialModel(
    name="sand",
    doc="Drucker-Prager elastoplastic sand (Klar et al. 2016), cohesionless.",
    parameters=SOLID_PARAMETERS
    + (Parameter("friction_angle", 30.0, "internal friction angle, degrees", gt=0.0, lt=90.0),),
    device_fields={**ELASTIC_FIELDS, "sand_alpha": float},
    device_values=lambda m: {**lame_values(m), "sand_alpha": cone_coefficient(m.friction_angle)},
    wave_speed=p_wave_speed,
    stress=stress,
    update=update,
)
