"""Fixed-corotated hyperelastic solid (Stomakhin et al. 2013 without plasticity)."""

from __future__ import annotations

from typing import Any

import warp as wp

from .base import Deformation, MaterialModel
from .common import ELASTIC_FIELDS, SOLID_PARAMETERS, fixed_corotated, lame_values, p_wave_speed, trial_deformation

wp.set_module_options({"enable_backward": False})


@wp.func
def stress(mat: Any, F: wp.mat33, C: wp.mat33, history: float):
    return fixed_corotated(mat.mu, mat.lam, F)


@wp.func
def update(mat: Any, F: wp.mat33, C: wp.mat33, history: float, dt: float):
    out = Deformation()
    out.F = trial_deformation(F, C, dt)  # Eq. 7; no plasticity
    out.history = history
    return out


MODEL = MaterialModel(
    name="elastic",
    doc=__doc__.strip(),
    parameters=SOLID_PARAMETERS,
    device_fields=ELASTIC_FIELDS,
    device_values=lame_values,
    wave_speed=p_wave_speed,
    stress=stress,
    update=update,
)
