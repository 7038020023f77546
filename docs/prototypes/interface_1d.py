"""A one-dimensional model of the level interface (docs/method.md, "Momentum across the
level interface"): an elastic bar whose halves meet at 1 m/s, the left half sampled
coarse, the right half fine (b = 2), in MLS-MPM with APIC transfers and quadratic
B-splines. It compares ways of coupling the two grids on total momentum (zero, a
conservation law) and kinetic energy, against the bar sampled fine everywhere:

* ``finest``: every particle fine, one fine grid;
* ``original``: every particle coarse, one coarse grid;
* ``ghosts``: today's scheme: each level scatters to its own grid and, as a ghost, to
  the other's where that grid is in use (coarse nodes reached by level 0; fine nodes
  around level 1), and gathers from its own grid only;
* ``blend``: a partition of unity: particle p scatters the share a(x_p) of itself to the
  coarse grid and 1 - a to the fine one, full stencils on both, and gathers the same
  shares back; a goes from 1 to 0 across a band of ``band`` coarse cells around the
  interface. Momentum is exact for any a.
* ``hanging``: each level on its own grid only; the fine nodes left of ``edge`` (the
  region's edge) that level 1 reaches are not unknowns of their own but hang on the
  coarse grid, as in adaptive finite elements: their mass and momentum are handed to the
  coarse nodes with the coarse B-spline weights at the node (restriction) and they take
  the coarse velocity interpolated there (prolongation, its transpose). Momentum is exact.

Run: ``python docs/prototypes/interface_1d.py`` (numpy only, a few seconds).
"""

from __future__ import annotations

import numpy as np

E, RHO = 2.0e4, 1000.0  # Pa, kg/m^3: a soft jelly, wave speed 4.5 m/s
DX = 0.05  # coarse spacing; fine = DX / 2
L0, LI, L1 = 0.4, 0.8, 1.2  # the bar, and the interface between the levels
DOMAIN = 1.6
T_END = 1.0


def weights(x, dx):
    """Quadratic B-spline: base node index, the 3 weights, the offsets x_i - x_p."""
    X = x / dx
    base = np.floor(X - 0.5).astype(int)
    fx = X - base
    w = np.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], axis=1)
    off = (np.arange(3)[None, :] - fx[:, None]) * dx
    return base, w, off


class Bar:
    def __init__(self, scheme: str, band: float = 2.0, shares: tuple[float, float] = (0.5, 0.5),
                 affine_kick: bool = False, band_gradient: bool = False, smooth: bool = False, edge: float = 0.25):
        self.scheme, self.band, self.shares, self.affine_kick = scheme, band, shares, affine_kick
        self.edge = LI + edge * DX  # hanging: the region's edge, in coarse cells right of the interface
        self.band_gradient, self.smooth = band_gradient, smooth
        xs, ms, lv = [], [], []
        for lo, hi, fine in ((L0, LI, scheme == "finest"), (LI, L1, scheme != "original")):
            h = (DX / 2 if fine else DX) / 2  # two particles per cell
            x = np.arange(lo + h / 2, hi, h)
            xs.append(x)
            ms.append(np.full(len(x), RHO * h))
            lv.append(np.full(len(x), int(fine)))
        self.x = np.concatenate(xs)
        self.m = np.concatenate(ms)
        self.V = self.m / RHO
        self.level = np.concatenate(lv)
        self.v = np.where(self.x < LI, 1.0, -1.0)
        self.C = np.zeros_like(self.x)
        self.F = np.ones_like(self.x)
        self.dt = 0.3 * (DX / 2) / np.sqrt(E / RHO)

    def band_position(self):
        """0 at the band's coarse side, 1 at its fine side."""
        w = self.band * DX
        return np.clip((self.x - (LI - w / 2)) / w, 0.0, 1.0)

    def coarse_share(self):
        """The share a_p each particle gives the coarse grid."""
        if self.scheme == "finest":
            return np.zeros_like(self.x)
        if self.scheme == "original":
            return np.ones_like(self.x)
        if self.scheme == "blend":
            s = self.band_position()
            return 1.0 - s * s * (3.0 - 2.0 * s) if self.smooth else 1.0 - s
        return (self.level == 0).astype(float)  # ghosts: own grid = level

    def scatter(self, dx, share):
        n = int(DOMAIN / dx) + 4 + 200
        mv, m = np.zeros(n), np.zeros(n)
        base, w, off = weights(self.x, dx)
        stress = E * (self.F - 1.0)
        affine = self.m * self.C - self.dt * self.V * stress * 4.0 / dx**2
        for k in range(3):
            idx = base + k
            wk = w[:, k] * share
            np.add.at(mv, idx, wk * (self.m * self.v + affine * off[:, k]))
            np.add.at(m, idx, wk * self.m)
        v = np.divide(mv, m, out=np.zeros(n), where=m > 0)
        return v, m

    def sums(self, dx, who, node_ok):
        """Momentum and mass of the particles ``who`` on the grid of spacing dx, only on
        the nodes where ``node_ok`` (None: all)."""
        n = int(DOMAIN / dx) + 4 + 200
        mv, m = np.zeros(n), np.zeros(n)
        base, w, off = weights(self.x, dx)
        affine = self.m * self.C - self.dt * self.V * E * (self.F - 1.0) * 4.0 / dx**2
        for k in range(3):
            idx = base + k
            wk = w[:, k] * who * (1.0 if node_ok is None else node_ok[idx])
            np.add.at(mv, idx, wk * (self.m * self.v + affine * off[:, k]))
            np.add.at(m, idx, wk * self.m)
        return mv, m

    def gather_masked(self, dx, vgrid, node_ok):
        base, w, off = weights(self.x, dx)
        idx = base[:, None] + np.arange(3)
        wm = w * node_ok[idx]
        return (wm * vgrid[idx]).sum(1), (wm * vgrid[idx] * off).sum(1) * 4.0 / dx**2

    def gather(self, dx, vgrid):
        base, w, off = weights(self.x, dx)
        v = (w * vgrid[base[:, None] + np.arange(3)]).sum(1)
        C = (w * vgrid[base[:, None] + np.arange(3)] * off).sum(1) * 4.0 / dx**2
        return v, C

    def step(self):
        a = self.coarse_share()
        if self.scheme == "bridge":
            # each level on its own grid only; where a coarse node and the fine node on
            # it both hold mass, the two take their common (mass-weighted) velocity: equal
            # and opposite impulses, node by node
            own0, own1 = self.level == 0, self.level == 1
            p0c, m0c = self.sums(DX, own0, None)
            p1f, m1f = self.sums(DX / 2, own1, None)
            vc = np.divide(p0c, m0c, out=np.zeros_like(p0c), where=m0c > 0)
            vf = np.divide(p1f, m1f, out=np.zeros_like(p1f), where=m1f > 0)
            n = min(len(vc), (len(vf) + 1) // 2)
            both = (m0c[:n] > 0) & (m1f[: 2 * n : 2] > 0)
            common = np.divide(m0c[:n] * vc[:n] + m1f[: 2 * n : 2] * vf[: 2 * n : 2], m0c[:n] + m1f[: 2 * n : 2],
                               out=np.zeros(n), where=both)
            vc[:n] = np.where(both, common, vc[:n])
            vf[: 2 * n : 2] = np.where(both, common, vf[: 2 * n : 2])
            v0, C0 = self.gather(DX, vc)
            v1, C1 = self.gather(DX / 2, vf)
            self.v = np.where(own0, v0, v1)
            self.C = np.where(own0, C0, C1)
        elif self.scheme == "hanging":
            own0, own1 = self.level == 0, self.level == 1
            p0c, m0c = self.sums(DX, own0, None)
            p1f, m1f = self.sums(DX / 2, own1, None)
            xf = np.arange(len(p1f)) * DX / 2
            hang = (xf < self.edge) & (m1f > 0)  # fine nodes outside the region
            base, w, _ = weights(xf, DX)
            idx = np.clip(base[:, None] + np.arange(3), 0, len(p0c) - 1)
            for k in range(3):  # restriction: the hanging nodes' sums onto the coarse nodes
                np.add.at(p0c, idx[hang, k], w[hang, k] * p1f[hang])
                np.add.at(m0c, idx[hang, k], w[hang, k] * m1f[hang])
            vc = np.divide(p0c, m0c, out=np.zeros_like(p0c), where=m0c > 0)
            vf = np.divide(p1f, m1f, out=np.zeros_like(p1f), where=m1f > 0)
            vf = np.where(hang, (w * vc[idx]).sum(1), vf)  # prolongation
            v0, C0 = self.gather(DX, vc)
            v1, C1 = self.gather(DX / 2, vf)
            self.v = np.where(own0, v0, v1)
            self.C = np.where(own0, C0, C1)
        elif self.scheme in ("ghosts", "kick"):
            own0, own1 = self.level == 0, self.level == 1
            _, mc0 = self.scatter(DX, own0.astype(float))  # where level 0 reaches the coarse grid
            reached = mc0 > 0
            lo_active = self.x[own1].min() - 2 * DX  # the fine grid: within 2 coarse cells of level 1
            # (momentum, mass) sums of each level on each grid: level 1 on the coarse grid
            # only where level 0 reaches it, level 0 on the fine grid only where it is active
            p0c, m0c = self.sums(DX, own0, None)
            p1c, m1c = self.sums(DX, own1, reached)
            p1f, m1f = self.sums(DX / 2, own1, None)
            p0f, m0f = self.sums(DX / 2, own0 & (self.x >= lo_active), None)
            vc = np.divide(p0c + p1c, m0c + m1c, out=np.zeros_like(p0c), where=m0c + m1c > 0)
            vf = np.divide(p0f + p1f, m0f + m1f, out=np.zeros_like(p0f), where=m0f + m1f > 0)
            v0, C0 = self.gather(DX, vc)
            v1, C1 = self.gather(DX / 2, vf)
            if self.scheme == "kick":  # docs/method.md: each level keeps x of its own grid's exchange
                def change(v, p, m):
                    return np.where(m > 0, v - np.divide(p, m, out=np.zeros_like(p), where=m > 0), 0.0)
                own_c, ghost_c = change(vc, p0c, m0c), change(vc, p1c, m1c)
                own_f, ghost_f = change(vf, p1f, m1f), change(vf, p0f, m0f)
                x0, x1 = self.shares
                active = (self.x >= lo_active).astype(float)
                ko_v, ko_C = self.gather(DX, own_c)
                kg_v, kg_C = self.gather(DX / 2, ghost_f)
                k0v, k0C = -(1 - x0) * ko_v + x1 * kg_v * active, -(1 - x0) * ko_C + x1 * kg_C * active
                ko_v, ko_C = self.gather(DX / 2, own_f)
                kg_v, kg_C = self.gather_masked(DX, ghost_c, reached)
                k1v, k1C = -(1 - x1) * ko_v + x0 * kg_v, -(1 - x1) * ko_C + x0 * kg_C
                v0, v1 = v0 + k0v, v1 + k1v
                if self.affine_kick:  # the kick's APIC part too (C carries no linear momentum)
                    C0, C1 = C0 + k0C, C1 + k1C
            self.v = np.where(own0, v0, v1)
            self.C = np.where(own0, C0, C1)
        else:
            vc, _ = self.scatter(DX, a)
            vf, _ = self.scatter(DX / 2, 1.0 - a)
            v0, C0 = self.gather(DX, vc)
            v1, C1 = self.gather(DX / 2, vf)
            self.v = a * v0 + (1.0 - a) * v1
            self.C = a * C0 + (1.0 - a) * C1
            if self.scheme == "blend" and self.band_gradient:
                # the gradient of the blended field a v_C + (1 - a) v_F has a third term,
                # grad a (v_C - v_F), which the two gathers do not see
                s = self.band_position()
                inside = (s > 0.0) & (s < 1.0)
                slope = np.where(inside, -(6.0 * s * (1.0 - s) if self.smooth else 1.0) / (self.band * DX), 0.0)
                self.C = self.C + slope * (v0 - v1)
        self.F = self.F * (1.0 + self.dt * self.C)
        self.x = self.x + self.dt * self.v

    def momentum(self):
        return float((self.m * self.v).sum())

    def kinetic(self):
        return float(0.5 * (self.m * self.v**2).sum())


def run(scheme: str, **kw) -> dict:
    bar = Bar(scheme, **kw)
    steps = int(T_END / bar.dt)
    half = 0.5 * float((bar.m * np.abs(bar.v)).sum())
    ke, drift = [], 0.0
    for s in range(steps):
        bar.step()
        ke.append(bar.kinetic())
        drift = max(drift, abs(bar.momentum()) / half)
        if not np.all(np.abs(bar.v) < 100.0) or bar.x.min() < 0.0 or bar.x.max() > DOMAIN:
            return {"drift": drift, "peaks": [], "ke_end_over_start": float("nan"), "unstable_at": s * bar.dt}
    ke = np.array(ke)
    peaks = [float(ke[i]) for i in range(1, len(ke) - 1) if ke[i] >= ke[i - 1] and ke[i] >= ke[i + 1] and ke[i] > 0.2 * ke[0]]
    return {"drift": drift, "peaks": peaks[:5], "ke_end_over_start": float(ke[-1] / ke[0])}


if __name__ == "__main__":
    for scheme, kw in (("finest", {}), ("original", {}), ("ghosts", {}), ("bridge", {}), ("kick", {"shares": (0.5, 0.5)}),
                       ("kick", {"shares": (1.0, 0.0)}), ("kick", {"shares": (0.0, 1.0)}),
                       ("kick", {"shares": (0.5, 0.5), "affine_kick": True}),
                       ("kick", {"shares": (1.0, 0.0), "affine_kick": True}),
                       ("kick", {"shares": (0.0, 1.0), "affine_kick": True}), ("blend", {"band": 2.0}),
                       ("blend", {"band": 8.0}), ("blend", {"band": 2.0, "band_gradient": True}),
                       ("blend", {"band": 4.0, "band_gradient": True}),
                       ("blend", {"band": 2.0, "band_gradient": True, "smooth": True}),
                       ("blend", {"band": 4.0, "band_gradient": True, "smooth": True}),
                       ("hanging", {"edge": 0.25}), ("hanging", {"edge": 1.0}), ("hanging", {"edge": 2.0})):
        r = run(scheme, **kw)
        label = scheme + "".join(f" ({k} {v})" for k, v in kw.items())
        print(f"{label:<32} momentum drift / one half's {r['drift']:.1e}   kinetic energy peaks "
              + " ".join(f"{p:.1f}" for p in r["peaks"])
              + (f"   unstable at {r['unstable_at']:.3f} s" if "unstable_at" in r else ""))
