"""Device functions shared by several material models (elasticity kernels)."""

from __future__ import annotations

import math

import warp as wp

from .base import Parameter

wp.set_module_options({"enable_backward": False})

# Scene parameters of every solid (the fluid has a bulk modulus instead).
SOLID_PARAMETERS = (
    Parameter("youngs_modulus", 1.0e5, "Young's modulus E, Pa", gt=0.0),
    Parameter("poisson_ratio", 0.3, "Poisson's ratio nu", gt=-1.0, lt=0.5),
)
ELASTIC_FIELDS = {"mu": float, "lam": float}


def lame(E: float, nu: float) -> tuple[float, float]:
    """Lame parameters (mu, lambda) from Young's modulus and Poisson's ratio."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def lame_values(m) -> dict[str, float]:
    mu, lam = lame(m.youngs_modulus, m.poisson_ratio)
    return {"mu": mu, "lam": lam}


def p_wave_speed(m) -> float:
    """sqrt((lambda + 2 mu) / rho): the fastest elastic wave of an isotropic solid."""
    mu, lam = lame(m.youngs_modulus, m.poisson_ratio)
    return math.sqrt((lam + 2.0 * mu) / m.density)


@wp.func
def trial_deformation(F: wp.mat33, C: wp.mat33, dt: float):
    # F <- (I + dt C) F: paper Eq. 7 with grad v ~ C (APIC)
    return (wp.identity(n=3, dtype=float) + dt * C) * F


@wp.func
def viscous_kirchhoff(eta: float, J: float, C: wp.mat33):
    # Newtonian viscous Cauchy stress eta (grad v + grad v^T), grad v ~ C (APIC)
    if eta == 0.0:
        return wp.mat33(0.0)
    return (eta * J) * (C + wp.transpose(C))


# Below this det F (a nearly flat or inverted particle) R comes from the SVD, whose
# sign conventions define it there; above it from the polar iteration
POLAR_MIN_DET = 0.01
POLAR_MAX_ITERATIONS = 16  # Higham's bound for condition numbers up to ~1e15 is 9
POLAR_TOLERANCE = 1.0e-12  # squared Frobenius change of an iteration: float32 round-off


@wp.func
def polar_rotation(F: wp.mat33):
    """R of the polar decomposition F = R S, for det F > 0, by Newton's iteration
    X <- (g X + X^-T / g) / 2 with Higham's Frobenius-norm scaling g = (|X^-1| / |X|)^1/2
    (N. J. Higham, "Computing the polar decomposition, with applications", SIAM J. Sci.
    Stat. Comput. 7, 1986). It converges quadratically: 3 iterations for strains of a few
    percent, 4-5 for strains of tens of percent, with a float32 stopping test. Against
    float64's polar factor its float32 result is off by ~2e-7 where ``wp.svd3``'s U V^T is
    off by up to 2e-2 (docs/benchmarks.md), at a third of the cost near F = I."""
    X = F
    for _ in range(POLAR_MAX_ITERATIONS):
        Xi = wp.inverse(X)
        g = wp.sqrt(wp.sqrt(wp.ddot(Xi, Xi) / wp.ddot(X, X)))
        Xn = 0.5 * (g * X + (1.0 / g) * wp.transpose(Xi))
        change = wp.ddot(Xn - X, Xn - X)
        X = Xn
        if change < POLAR_TOLERANCE:
            break
    return X


@wp.func
def fixed_corotated(mu: float, lam: float, F: wp.mat33):
    # tau = 2 mu (F - R) F^T + lam (J - 1) J I   (paper Section 4.1)
    J = wp.determinant(F)
    R = wp.mat33()
    if J > POLAR_MIN_DET:
        R = polar_rotation(F)
    else:
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
