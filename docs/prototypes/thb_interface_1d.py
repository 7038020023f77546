"""The level interface as one basis: truncated hierarchical B-splines (THB) in 1D.

The bar of ``interface_1d.py`` (an elastic bar whose halves meet at 1 m/s), with the
levels meeting at ``SPLIT`` and a refinement factor b = 3. Instead of two grids that
each particle scatters to and only one of which it gathers from (today's ghosts), every
particle uses one basis: the fine quadratic B-splines whose support lies in the refined
part, and the coarse ones that reach outside it, each *truncated* (the fine B-splines
that are themselves in the basis are taken out of its refinement relation). Those
functions are a partition of unity and reproduce linear fields (coarse and fine centres
as they are), so MPM on them conserves mass and momentum exactly with no exchange term.
The refinement relation needs nested knots: odd b only (b = 2 has no exact one).

Two force and gradient variants: MLS's (the force and F's update from C = B D^-1, with D
each particle's own inertia over the basis) and the basis' exact gradients (APIC for C,
the gradient of the basis for the force and F's update). Run:
``python docs/prototypes/thb_interface_1d.py`` (numpy only, a few seconds); the figures
are in docs/method.md ("Momentum across the level interface").
"""

from __future__ import annotations

import numpy as np

E, RHO = 2.0e4, 1000.0  # Pa, kg/m^3: a soft jelly, wave speed 4.5 m/s
DX = 0.05  # coarse spacing
B = 3  # refinement factor (odd)
L0, MEET, L1 = 0.4, 0.8, 1.2  # the bar, and where its halves meet
DOMAIN = 1.6
T_END = 1.0


def bspline(t):
    t = np.abs(t)
    return np.where(t < 0.5, 0.75 - t * t, np.where(t < 1.5, 0.5 * (1.5 - t) ** 2, 0.0))


def refinement_relation(b: int):
    """Offsets k and coefficients c_k with B(t) = sum_k c_k B(b t - k), and the residual
    of that fit (round-off for odd b, 2% for b = 2)."""
    ks = np.arange(-(b + 1), b + 2)
    t = np.linspace(-2.0, 2.0, 4001)
    A = bspline(b * t[:, None] - ks[None, :])
    c, *_ = np.linalg.lstsq(A, bspline(t), rcond=None)
    return ks, c, float(np.abs(A @ c - bspline(t)).max())


class Basis:
    """Basis functions (their centres ``xa``) of one uniform grid, or THB's over [a, inf)."""

    def __init__(self, kind: str, a: float = 0.0):
        H, h = DX, DX / B
        nC, nF = int(DOMAIN / H) + 3, int(DOMAIN / h) + 3
        self.kind, self.h = kind, {"coarse": H, "fine": h}.get(kind, h)
        if kind == "coarse":
            self.xa = np.arange(nC) * H
        elif kind == "fine":
            self.xa = np.arange(nF) * h
        else:
            self.ks, self.c, err = refinement_relation(B)
            assert err < 1e-12, f"no exact refinement relation for b = {B}"
            j, i = np.arange(nF), np.arange(nC)
            self.fine_on = j[j * h - 1.5 * h >= a - 1e-12]  # support inside the refined part
            self.coarse_on = i[i * H - 1.5 * H < a - 1e-12]  # support reaching outside it
            self.active = np.zeros(nF + 2 * B + 2, bool)
            self.active[self.fine_on] = True
            self.xa = np.concatenate([self.coarse_on * H, self.fine_on * h])

    def eval(self, x):
        """Values of every function at the points x (points x functions)."""
        if self.kind != "thb":
            return bspline((x[:, None] - self.xa[None, :]) / self.h)
        H, h = DX, DX / B
        coarse = bspline((x[:, None] - self.coarse_on[None, :] * H) / H)
        for col, i in enumerate(self.coarse_on):  # truncation
            for k, ck in zip(self.ks, self.c):
                j = B * i + k
                if 0 <= j < len(self.active) and self.active[j]:
                    coarse[:, col] -= ck * bspline((x - j * h) / h)
        return np.concatenate([coarse, bspline((x[:, None] - self.fine_on[None, :] * h) / h)], axis=1)

    def grad(self, x, eps: float = 1e-7):
        return (self.eval(x + eps) - self.eval(x - eps)) / (2.0 * eps)


class Bar:
    def __init__(self, scheme: str, split: float, exact_gradients: bool = False):
        self.scheme, self.exact = scheme, exact_gradients
        xs, ms, lv = [], [], []
        for lo, hi, fine in ((L0, split, scheme == "finest"), (split, L1, scheme != "original")):
            sp = (DX / B if fine else DX) / 2  # two particles per cell of their level
            x = np.arange(lo + sp / 2, hi, sp)
            xs.append(x)
            ms.append(np.full(len(x), RHO * sp))
            lv.append(np.full(len(x), int(fine)))
        self.x, self.m, self.level = np.concatenate(xs), np.concatenate(ms), np.concatenate(lv)
        self.V = self.m / RHO
        self.v = np.where(self.x < MEET, 1.0, -1.0)
        self.C = np.zeros_like(self.x)
        self.F = np.ones_like(self.x)
        self.dt = 0.3 * (DX / B) / np.sqrt(E / RHO)
        self.basis = {"finest": Basis("fine"), "original": Basis("coarse")}.get(scheme) or Basis("thb", split - 0.5 * DX)

    def step(self):
        W, xa = self.basis.eval(self.x), self.basis.xa
        d = xa[None, :] - self.x[:, None]
        D = (W * d * d).sum(1)  # each particle's inertia over the basis (dx^2 / 4 on a uniform grid)
        stress = E * (self.F - 1.0)
        mv = W * (self.m * self.v)[:, None] + W * d * (self.m * self.C)[:, None]
        if self.exact:
            G = self.basis.grad(self.x)
            mv -= self.dt * (self.V * stress)[:, None] * G
        else:
            mv -= W * d * (self.dt * self.V * stress / D)[:, None]
        mv, m = mv.sum(0), (W * self.m[:, None]).sum(0)
        vg = np.divide(mv, m, out=np.zeros_like(mv), where=m > 1e-12)
        self.v = (W * vg).sum(1)
        self.C = (W * vg * d).sum(1) / D
        grad_v = (self.basis.grad(self.x) * vg).sum(1) if self.exact else self.C
        self.F = self.F * (1.0 + self.dt * grad_v)
        self.x = self.x + self.dt * self.v


def run(scheme: str, split: float, exact_gradients: bool = False) -> dict:
    bar = Bar(scheme, split, exact_gradients)
    half = 0.5 * float((bar.m * np.abs(bar.v)).sum())
    length0 = bar.x.max() - bar.x.min()
    ke, drift = [], 0.0
    for _ in range(int(T_END / bar.dt)):
        bar.step()
        ke.append(0.5 * float((bar.m * bar.v**2).sum()))
        drift = max(drift, abs(float((bar.m * bar.v).sum())) / half)
    ke = np.array(ke)
    peaks = [float(ke[i]) for i in range(1, len(ke) - 1)
             if ke[i] >= ke[i - 1] and ke[i] >= ke[i + 1] and ke[i] > 0.2 * ke[0]]
    return {"drift": drift, "peaks": peaks[:5], "stretch": float((bar.x.max() - bar.x.min()) / length0)}


if __name__ == "__main__":
    _, c, err = refinement_relation(B)
    print(f"b = {B}: refinement coefficients {np.round(c * B * B, 6)} / b^2 (residual {err:.1e}); "
          f"b = 2: residual {refinement_relation(2)[2]:.1e}")
    for split in (0.6, 0.8, 1.0):
        print(f"levels meet at {split} m (the halves at {MEET} m)")
        for scheme, exact in (("finest", False), ("original", False), ("thb", False), ("thb", True)):
            r = run(scheme, split, exact)
            label = scheme + (" exact gradients" if exact else " MLS" if scheme == "thb" else "")
            print(f"  {label:<22} momentum drift / one half's {r['drift']:.1e}   kinetic energy peaks "
                  + " ".join(f"{p:.1f}" for p in r["peaks"]) + f"   length at the end / at the start {r['stretch']:.2f}")
