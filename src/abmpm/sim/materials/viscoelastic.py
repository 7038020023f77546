"""Fixed-corotated solid whose deviatoric strain relaxes (Maxwell) plus viscous damping."""

from __future__ import annotations

from typing import Any

import warp as wp

from .base import Deformation, MaterialModel, Parameter
from .common import (
    ELASTIC_FIELDS,
    SOLID_PARAMETERS,
    fixed_corotated,
    from_hencky,
    hencky,
    lame_values,
    p_wave_speed,
    trial_deformation,
    viscous_kirchhoff,
)

wp.set_module_options({"enable_backward": False})


@wp.func
def stress(mat: Any, F: wp.mat33, C: wp.mat33, history: float):
    # elastic part plus Kelvin-Voigt damping
    return fixed_corotated(mat.mu, mat.lam, F) + viscous_kirchhoff(mat.viscosity, wp.determinant(F), C)


@wp.func
def update(mat: Any, F: wp.mat33, C: wp.mat33, history: float, dt: float):
    # Eq. 7, then the deviatoric Hencky strain decays with the relaxation time
    # (volume is kept): the return mapping of this model (Eq. 14)
    h = hencky(trial_deformation(F, C, dt))
    vol = (h.eps[0] + h.eps[1] + h.eps[2]) / 3.0
    decay = wp.exp(-dt / mat.relaxation_time)
    out = Deformation()
    out.F = from_hencky(h, wp.vec3(vol) + decay * (h.eps - wp.vec3(vol)))
    out.history = history
    return out


MODEL = MaterialModel(
    name="viscoelastic",
    doc=__doc__.strip(),
    parameters=SOLID_PARAMETERS
    + (
        Parameter("viscosity", 1.0, "Kelvin-Voigt damping viscosity, Pa s", ge=0.0),
        Parameter("relaxation_time", 0.5, "Maxwell relaxation time of shear strain, s", gt=0.0),
    ),
    device_fields={**ELASTIC_FIELDS, "viscosity": float, "relaxation_time": float},
    device_values=lambda m: {**lame_values(m), "viscosity": m.viscosity, "relaxation_time": m.relaxation_time},
    wave_speed=p_wave_speed,
    stress=stress,
    update=update,
)
