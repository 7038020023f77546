"""The partition coupling in one dimension (docs/method.md, "The two grids as one basis"): the
elastic bar of ``interface_1d.py`` (halves meeting at 1 m/s, the left coarse, the right fine,
b = 2), MLS-MPM with APIC, every particle transferring with one partition of unity made of the
coarse B-splines weighted by a node share a(x_I) and the fine ones by 1 - a(x_i), normalised.
The share falls from 1 to 0 across a band of ``width`` coarse cells centred at ``centre``.

Run: ``python docs/prototypes/partition_1d.py`` (exact gradients of the normalised weights for
the force and F) or ``... mls`` (MLS's force with each particle's own D, which loses energy).
Momentum is exact either way; with exact gradients the kinetic-energy peaks lie between
original's and finest's wherever the band lies inside the fine particles, and the bar tears
where it lies among the coarse ones (coarse particles the only samples of fine functions).
"""
import sys
import numpy as np
E, RHO = 2.0e4, 1000.0
DX = 0.05
L0, LI, L1 = 0.4, 0.8, 1.2
DOMAIN, T_END = 1.6, 1.0

def N(r):
    a = np.abs(r)
    return np.where(a < 0.5, 0.75 - a * a, np.where(a < 1.5, 0.5 * (1.5 - a) ** 2, 0.0))

def dN(r):
    a = np.abs(r); s = np.sign(r)
    return np.where(a < 0.5, -2 * r, np.where(a < 1.5, -(1.5 - a) * s, 0.0))

class Bar:
    def __init__(self, share, all_fine=False, all_coarse=False, affine="apic", level_x=LI):
        """Particles fine right of ``level_x`` (the halves meet at LI either way)."""
        self.share, self.affine = share, affine
        xs, ms = [], []
        for lo, hi, fine in ((L0, level_x, all_fine), (level_x, L1, not all_coarse)):
            h = (DX / 2 if fine else DX) / 2
            x = np.arange(lo + h / 2, hi, h); xs.append(x); ms.append(np.full(len(x), RHO * h))
        self.x = np.concatenate(xs); self.m = np.concatenate(ms); self.V = self.m / RHO
        self.v = np.where(self.x < LI, 1.0, -1.0); self.C = np.zeros_like(self.x); self.F = np.ones_like(self.x)
        self.dt = 0.3 * (DX / 2) / np.sqrt(E / RHO)
        nc, nf = int(DOMAIN / DX) + 3, int(DOMAIN / (DX / 2)) + 3
        self.xc = np.arange(nc) * DX; self.xf = np.arange(nf) * DX / 2
        self.ac = share(self.xc); self.af = 1.0 - share(self.xf)

    def basis(self):
        x = self.x
        bc = np.floor(x / DX - 0.5).astype(int); bf = np.floor(x / (DX / 2) - 0.5).astype(int)
        ic = bc[:, None] + np.arange(3); i_f = bf[:, None] + np.arange(3)
        rc = self.ac[ic] * N((x[:, None] - self.xc[ic]) / DX); gc = self.ac[ic] * dN((x[:, None] - self.xc[ic]) / DX) / DX
        rf = self.af[i_f] * N((x[:, None] - self.xf[i_f]) / (DX / 2)); gf = self.af[i_f] * dN((x[:, None] - self.xf[i_f]) / (DX / 2)) / (DX / 2)
        S = rc.sum(1) + rf.sum(1); dS = gc.sum(1) + gf.sum(1)
        W = np.concatenate([rc, rf], 1) / S[:, None]
        G = np.concatenate([gc, gf], 1) / S[:, None] - np.concatenate([rc, rf], 1) * (dS / S**2)[:, None]
        idx = np.concatenate([ic, i_f + len(self.xc)], 1)
        pos = np.concatenate([self.xc[ic], self.xf[i_f]], 1)
        return W, G, idx, pos

    def step(self):
        W, G, idx, pos = self.basis()
        n = len(self.xc) + len(self.xf)
        xbar = (W * pos).sum(1)
        d = pos - xbar[:, None]
        stress = E * (self.F - 1.0)
        m = np.zeros(n); p = np.zeros(n); f = np.zeros(n)
        np.add.at(m, idx, W * self.m[:, None])
        np.add.at(p, idx, W * (self.m * self.v)[:, None] + W * (self.m * self.C)[:, None] * d)
        np.add.at(f, idx, -(self.V * stress)[:, None] * G)
        vn = np.divide(p + self.dt * f, m, out=np.zeros(n), where=m > 1e-12)
        vg = vn[idx]
        self.v = (W * vg).sum(1)
        grad = (G * vg).sum(1)
        if self.affine == "apic":
            D = (W * d * d).sum(1)
            self.C = (W * vg * d).sum(1) / D
        else:
            self.C = grad
        self.F = self.F * (1.0 + self.dt * grad)
        self.x = self.x + self.dt * self.v

def run(bar):
    """Momentum drift over one half's, the first five kinetic-energy peaks, when it blew up."""
    steps = int(T_END / bar.dt)
    half = 0.5 * float((bar.m * np.abs(bar.v)).sum())
    ke, drift = [], 0.0
    for s in range(steps):
        bar.step()
        ke.append(0.5 * (bar.m * bar.v**2).sum())
        drift = max(drift, abs((bar.m * bar.v).sum()) / half)
        if not np.all(np.abs(bar.v) < 100) or bar.x.min() < DX * 2 or bar.x.max() > DOMAIN - 2 * DX:
            return drift, [], s * bar.dt, bar
    ke = np.array(ke)
    peaks = [float(ke[i]) for i in range(1, len(ke) - 1) if ke[i] >= ke[i - 1] and ke[i] >= ke[i + 1] and ke[i] > 0.2 * ke[0]]
    return drift, peaks[:5], None, bar

def linear_share(center, width):
    return lambda x: np.clip((center + width / 2 - x) / width, 0.0, 1.0)

class BarMLS(Bar):
    """MLS: the force folded in the affine term with the particle's own D; F updated with C."""

    def step(self):
        W, G, idx, pos = self.basis()
        n = len(self.xc) + len(self.xf)
        xbar = (W * pos).sum(1)
        d = pos - xbar[:, None]
        D = (W * d * d).sum(1)
        affine = self.m * self.C - self.dt * self.V * E * (self.F - 1.0) / D
        m = np.zeros(n)
        p = np.zeros(n)
        np.add.at(m, idx, W * self.m[:, None])
        np.add.at(p, idx, W * (self.m * self.v)[:, None] + W * affine[:, None] * d)
        vg = np.divide(p, m, out=np.zeros(n), where=m > 1e-12)[idx]
        self.v = (W * vg).sum(1)
        self.C = (W * vg * d).sum(1) / D
        self.F = self.F * (1.0 + self.dt * self.C)
        self.x = self.x + self.dt * self.v


if __name__ == "__main__":
    mls = len(sys.argv) > 1 and sys.argv[1] == "mls"
    affine = "apic"
    if mls:
        Bar = BarMLS  # noqa: F811
    cases = [("finest", dict(all_fine=True), lambda x: np.zeros_like(x)),
             ("original", dict(all_coarse=True), lambda x: np.ones_like(x))]
    for c in (LI, LI + DX, LI + 2 * DX, LI - DX):
        for w in (1, 2, 4):
            cases.append((f"PU band centre {c:.2f} width {w} cells", {}, linear_share(c, w * DX)))
    for level_x in (0.6, 0.7, 0.9, 1.0):  # the collision inside the fine part, or inside the coarse part
        for off, w in ((0.5, 1), (1.0, 2)):
            c = level_x + off * DX
            cases.append((f"levels meet {level_x:.1f}, band {c:.3f} w {w}", {"level_x": level_x},
                          linear_share(c, w * DX)))
    for name, kw, share in cases:
        drift, peaks, unstable, bar = run(Bar(share, affine=affine, **kw))
        print(f"{name:<36} drift {drift:.1e} peaks " + " ".join(f"{q:.1f}" for q in peaks)
              + (f" unstable {unstable:.3f}" if unstable is not None else "")
              + f"  len {bar.x.max() - bar.x.min():.3f}", flush=True)
