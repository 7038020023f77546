"""Constitutive models: the one place to touch when adding a material.

Each particle carries a material index into an array of :class:`MaterialParams`.
Two device functions dispatch on ``params.model``:

* :func:`kirchhoff_stress` (fluids: :func:`fluid_stress`, from J alone) gives tau = P F^T = J sigma, used by the MLS-MPM force
  of paper Eq. 9 (f_i = -4/dx^2 V0 tau w_ip (x_i - x_p)).
* :func:`update_deformation` advances F by Eq. 7 and applies the plastic / relaxation return mapping to
  the trial deformation gradient after Eq. 7 (paper Eqs. 13-14) and updates the
  scalar state (fluid: volume ratio J; snow: J_P; sand: accumulated volumetric
  correction).

To add a model: a new ``MODEL_*`` id, a branch in both device functions, a branch in
:func:`material_params` (scene parameters -> struct) and in :func:`wave_speed`.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})

from ..scene import model as sm

MODEL_FLUID = wp.constant(0)
MODEL_ELASTIC = wp.constant(1)
MODEL_VISCOELASTIC = wp.constant(2)
MODEL_SAND = wp.constant(3)
MODEL_SNOW = wp.constant(4)

MODEL_IDS = {"fluid": 0, "elastic": 1, "viscoelastic": 2, "sand": 3, "snow": 4}


@wp.struct
class MaterialParams:
    model: int
    density: float
    mu: float  # shear modulus (Lame mu), Pa
    lam: float  # Lame lambda, Pa
    bulk: float  # fluid bulk modulus, Pa
    gamma: float  # fluid Tait exponent
    viscosity: float  # dynamic viscosity, Pa s (fluid, viscoelastic)
    relaxation_time: float  # viscoelastic Maxwell time, s
    sand_alpha: float  # Drucker-Prager cone coefficient (Klar et al. 2016, Eq. 27)
    theta_c: float  # snow critical compression
    theta_s: float  # snow critical stretch
    hardening: float  # snow hardening coefficient xi


def lame(E: float, nu: float) -> tuple[float, float]:
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def material_params(m) -> MaterialParams:
    """Scene material (pydantic model) -> device struct, in SI units."""
    p = MaterialParams()
    p.model = MODEL_IDS[m.model]
    p.density = m.density
    p.mu = p.lam = p.bulk = p.viscosity = 0.0
    p.gamma = 1.0
    p.relaxation_time = 1.0
    p.sand_alpha = p.theta_c = p.theta_s = p.hardening = 0.0
    if isinstance(m, sm.Fluid):
        p.bulk, p.gamma, p.viscosity = m.bulk_modulus, m.gamma, m.viscosity
    else:
        p.mu, p.lam = lame(m.youngs_modulus, m.poisson_ratio)
    if isinstance(m, sm.Viscoelastic):
        p.viscosity, p.relaxation_time = m.viscosity, m.relaxation_time
    if isinstance(m, sm.Sand):
        s = math.sin(math.radians(m.friction_angle))
        p.sand_alpha = math.sqrt(2.0 / 3.0) * 2.0 * s / (3.0 - s)
    if isinstance(m, sm.Snow):
        p.theta_c, p.theta_s, p.hardening = m.critical_compression, m.critical_stretch, m.hardening
    return p


def wave_speed(m) -> float:
    """Fastest elastic (P-) wave speed of a material: the CFL time step uses it."""
    if isinstance(m, sm.Fluid):
        return math.sqrt(m.bulk_modulus / m.density)
    mu, lam = lame(m.youngs_modulus, m.poisson_ratio)
    c = math.sqrt((lam + 2.0 * mu) / m.density)
    if isinstance(m, sm.Snow):
        # hardening stiffens compressed snow; allow for J_P down to 1 - 10 theta_c
        c *= math.exp(0.5 * m.hardening * min(1.0, 10.0 * m.critical_compression))
    return c


def pressure_from_J(bulk: float | np.ndarray, gamma: float, J):
    """Weakly compressible equation of state (host side, for diagnostics and tests)."""
    return bulk * (np.power(J, -gamma) - 1.0) / gamma


# --------------------------------------------------------------------------- device functions


@wp.func
def tait_power(mat: MaterialParams, J: float):
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
def fluid_pressure(mat: MaterialParams, J: float):
    # Tait equation of state p = K (J^-gamma - 1) / gamma, so dp/dJ = -K at J = 1.
    return mat.bulk * (tait_power(mat, J) - 1.0) / mat.gamma


@wp.func
def stiffening(mat: MaterialParams, J: float):
    """Sound speed of a fluid compressed to J over its speed at rest: dp/drho =
    K J^(1 - gamma) / rho0, so sqrt(J^(1 - gamma)), > 1 under compression. An impact
    compresses the fluid and its sound speed grows with it; the CFL step must follow
    (host ``wave_speed`` is the speed at rest). Solids and expanded fluids: 1."""
    if mat.model != MODEL_FLUID or J >= 1.0 or J <= 0.0:
        return 1.0
    return wp.sqrt(J * tait_power(mat, J))


@wp.func
def viscous_kirchhoff(eta: float, J: float, C: wp.mat33):
    # Newtonian viscous Cauchy stress eta (grad v + grad v^T), grad v ~ C (APIC)
    if eta == 0.0:
        return wp.mat33(0.0)
    return (eta * J) * (C + wp.transpose(C))




@wp.func
def fixed_corotated(mu: float, lam: float, F: wp.mat33):
    # tau = 2 mu (F - R) F^T + lam (J - 1) J I   (paper Section 4.1)
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, sig, V)
    R = U * wp.transpose(V)
    J = sig[0] * sig[1] * sig[2]
    return 2.0 * mu * (F - R) * wp.transpose(F) + wp.identity(n=3, dtype=float) * (lam * (J - 1.0) * J)


@wp.func
def safe_log(s: float):
    return wp.log(wp.max(s, 1.0e-6))


@wp.struct
class Hencky:
    """F = U exp(diag(eps)) V^T: the principal log (Hencky) strains of F."""

    U: wp.mat33
    eps: wp.vec3
    V: wp.mat33


@wp.func
def hencky(F: wp.mat33):
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, sig, V)
    h = Hencky()
    h.U = U
    h.V = V
    h.eps = wp.vec3(safe_log(sig[0]), safe_log(sig[1]), safe_log(sig[2]))
    return h


@wp.func
def from_hencky(h: Hencky, eps: wp.vec3):
    # U exp(diag(eps)) V^T with new principal log strains
    return h.U * wp.diag(wp.vec3(wp.exp(eps[0]), wp.exp(eps[1]), wp.exp(eps[2]))) * wp.transpose(h.V)


@wp.func
def hencky_kirchhoff(mu: float, lam: float, F: wp.mat33):
    # St. Venant-Kirchhoff in log strain: tau = U (2 mu eps + lam tr(eps) I) U^T
    h = hencky(F)
    tr = h.eps[0] + h.eps[1] + h.eps[2]
    d = 2.0 * mu * h.eps + wp.vec3(lam * tr)
    return h.U * wp.diag(d) * wp.transpose(h.U)


@wp.func
def fluid_stress(mat: MaterialParams, J: float, C: wp.mat33):
    # A fluid keeps no shear memory, only its volume ratio J (kept in the particle's
    # scalar state; its F stays the identity): no SVD, no F traffic for fluids.
    return wp.identity(n=3, dtype=float) * (-fluid_pressure(mat, J) * J) + viscous_kirchhoff(mat.viscosity, J, C)


@wp.func
def solid_stress(mat: MaterialParams, F: wp.mat33, C: wp.mat33, plastic: float):
    if mat.model == MODEL_SAND:
        return hencky_kirchhoff(mat.mu, mat.lam, F)
    if mat.model == MODEL_SNOW:
        # hardening: stiffer when compressed (J_P < 1), Stomakhin et al. 2013 Eq. 2
        h = wp.exp(mat.hardening * (1.0 - plastic))
        return fixed_corotated(mat.mu * h, mat.lam * h, F)
    tau = fixed_corotated(mat.mu, mat.lam, F)
    if mat.model == MODEL_VISCOELASTIC:
        tau = tau + viscous_kirchhoff(mat.viscosity, wp.determinant(F), C)
    return tau


@wp.func
def kirchhoff_stress(mat: MaterialParams, F: wp.mat33, C: wp.mat33, plastic: float):
    if mat.model == MODEL_FLUID:
        return fluid_stress(mat, plastic, C)
    return solid_stress(mat, F, C, plastic)


@wp.struct
class Deformation:
    F: wp.mat33
    plastic: float


@wp.func
def sand_return_mapping(mat: MaterialParams, F: wp.mat33, plastic: float):
    # Drucker-Prager projection in Hencky strain (Klar et al. 2016, Section 7.3.1)
    h = hencky(F)
    eps = h.eps
    tr = eps[0] + eps[1] + eps[2]
    out = Deformation()
    out.plastic = plastic
    if tr >= 0.0:
        # expansion: cohesionless sand carries no tension, project to the cone tip
        out.F = h.U * wp.transpose(h.V)
        out.plastic = plastic + tr
        return out
    dev = eps - wp.vec3(tr / 3.0)
    dev_norm = wp.length(dev)
    dgamma = dev_norm + (3.0 * mat.lam + 2.0 * mat.mu) / (2.0 * mat.mu) * tr * mat.sand_alpha
    if dgamma <= 0.0 or dev_norm < 1.0e-12:
        out.F = F  # inside the yield cone
        return out
    out.F = from_hencky(h, eps - (dgamma / dev_norm) * dev)
    return out


@wp.func
def snow_return_mapping(mat: MaterialParams, F: wp.mat33, plastic: float):
    # clamp singular values to [1 - theta_c, 1 + theta_s]; the rest goes to F_P (Eq. 14)
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, sig, V)
    J_old = sig[0] * sig[1] * sig[2]
    for a in range(3):
        sig[a] = wp.clamp(sig[a], 1.0 - mat.theta_c, 1.0 + mat.theta_s)
    J_new = sig[0] * sig[1] * sig[2]
    out = Deformation()
    out.F = U * wp.diag(sig) * wp.transpose(V)
    out.plastic = plastic * J_old / J_new
    return out


@wp.func
def maxwell_relaxation(mat: MaterialParams, F: wp.mat33, dt: float):
    # the deviatoric Hencky strain decays with the relaxation time; volume is kept
    h = hencky(F)
    vol = (h.eps[0] + h.eps[1] + h.eps[2]) / 3.0
    decay = wp.exp(-dt / mat.relaxation_time)
    return from_hencky(h, wp.vec3(vol) + decay * (h.eps - wp.vec3(vol)))


@wp.func
def fluid_volume_update(J: float, C: wp.mat33, dt: float):
    # J <- det(I + dt C) J: the determinant of Eq. 7 (a fluid's F stays the identity)
    return wp.determinant(wp.identity(n=3, dtype=float) + dt * C) * J


@wp.func
def update_deformation(mat: MaterialParams, F: wp.mat33, C: wp.mat33, plastic: float, dt: float):
    """F <- (I + dt C) F (paper Eq. 7), then the model's return mapping (Eqs. 13-14)."""
    out = Deformation()
    out.plastic = plastic
    if mat.model == MODEL_FLUID:
        out.F = F
        out.plastic = fluid_volume_update(plastic, C, dt)
        return out
    F_trial = (wp.identity(n=3, dtype=float) + dt * C) * F
    out.F = F_trial
    if mat.model == MODEL_SAND:
        out = sand_return_mapping(mat, F_trial, plastic)
    elif mat.model == MODEL_SNOW:
        out = snow_return_mapping(mat, F_trial, plastic)
    elif mat.model == MODEL_VISCOELASTIC:
        out.F = maxwell_relaxation(mat, F_trial, dt)
    return out
