"""The partition coupling in three dimensions, before it went into the solver (docs/method.md,
"The two grids as one basis"): the interface suite's free jelly bar (halves meeting at 1 m/s,
the right half fine), two dense grids, every particle transferring with the coarse B-splines
weighted by a node share a and the fine ones by 1 - a, normalised; exact gradients in the band
(``mixed``: MLS for particles whose functions are one grid's alone, as sim/partition.py does).
Prints momentum drift and kinetic-energy peaks per mode: ``python docs/prototypes/partition_3d.py
[b] [seconds]`` (a few minutes at b = 2 on one core)."""
import sys, time
import numpy as np
import warp as wp
wp.config.quiet = True
wp.init()
wp.set_module_options({"enable_backward": False})

E, NU, RHO = 2.0e4, 0.3, 1000.0
MU, LAM = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))
DOM = wp.vec3(1.6, 1.0, 1.0)

@wp.func
def bsp(r: float):
    a = wp.abs(r)
    if a < 0.5:
        return 0.75 - a * a
    if a < 1.5:
        return 0.5 * (1.5 - a) * (1.5 - a)
    return 0.0

@wp.func
def dbsp(r: float):
    a = wp.abs(r)
    if a < 0.5:
        return -2.0 * r
    if a < 1.5:
        return -(1.5 - a) * wp.sign(r)
    return 0.0

@wp.struct
class Grid:
    dx: float
    n: wp.vec3i
    share: wp.array3d(dtype=float)  # this grid's node share (a coarse, 1 - a fine)
    m: wp.array3d(dtype=float)
    p: wp.array3d(dtype=wp.vec3)

@wp.func
def node_w(g: Grid, x: wp.vec3, base: wp.vec3i, i: int, j: int, k: int):
    # raw weight r and gradient of node base + (i, j, k)
    I = base + wp.vec3i(i, j, k)
    X = x / g.dx
    rx = X[0] - float(I[0]); ry = X[1] - float(I[1]); rz = X[2] - float(I[2])
    s = g.share[I[0], I[1], I[2]]
    w = s * bsp(rx) * bsp(ry) * bsp(rz)
    gr = s * wp.vec3(dbsp(rx) * bsp(ry) * bsp(rz), bsp(rx) * dbsp(ry) * bsp(rz), bsp(rx) * bsp(ry) * dbsp(rz)) / g.dx
    return w, gr

@wp.func
def base_of(g: Grid, x: wp.vec3):
    X = x / g.dx
    return wp.vec3i(int(X[0] - 0.5), int(X[1] - 0.5), int(X[2] - 0.5))

@wp.func
def npos(g: Grid, base: wp.vec3i, i: int, j: int, k: int):
    return wp.vec3(float(base[0] + i), float(base[1] + j), float(base[2] + k)) * g.dx

@wp.func
def sums(g: Grid, x: wp.vec3):
    base = base_of(g, x)
    S = float(0.0); dS = wp.vec3(); X = wp.vec3()
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w, gr = node_w(g, x, base, i, j, k)
                S += w; dS += gr; X += w * npos(g, base, i, j, k)
    return S, dS, X

@wp.func
def tau_of(F: wp.mat33):
    U = wp.mat33(); sig = wp.vec3(); V = wp.mat33()
    wp.svd3(F, U, sig, V)
    R = U * wp.transpose(V)
    J = sig[0] * sig[1] * sig[2]
    return 2.0 * MU * (F - R) * wp.transpose(F) + LAM * (J - 1.0) * J * wp.identity(n=3, dtype=float)

@wp.func
def scatter(g: Grid, x: wp.vec3, S: float, dS: wp.vec3, xbar: wp.vec3, m: float, mv: wp.vec3, mC: wp.mat33,
            stress: wp.mat33, mls: int):
    base = base_of(g, x)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                r, gr = node_w(g, x, base, i, j, k)
                if r != 0.0 or wp.length(gr) != 0.0:
                    W = r / S
                    gW = (gr - W * dS) / S
                    if mls != 0:
                        gW = W * 4.0 / (g.dx * g.dx) * (npos(g, base, i, j, k) - xbar)
                    I = base + wp.vec3i(i, j, k)
                    wp.atomic_add(g.m, I[0], I[1], I[2], W * m)
                    wp.atomic_add(g.p, I[0], I[1], I[2], W * (mv + mC * (npos(g, base, i, j, k) - xbar)) + stress * gW)

@wp.kernel
def p2g(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
        F: wp.array(dtype=wp.mat33), mass: wp.array(dtype=float), vol: wp.array(dtype=float), gc: Grid, gf: Grid,
        dt: float, mixed: int):
    p = wp.tid()
    Sc, dSc, Xc = sums(gc, x[p])
    Sf, dSf, Xf = sums(gf, x[p])
    S = Sc + Sf
    dS = dSc + dSf
    xbar = (Xc + Xf) / S
    stress = -dt * vol[p] * tau_of(F[p])
    mls = int(0)
    if mixed != 0 and (Sc == 0.0 or Sf == 0.0):
        mls = 1
    scatter(gc, x[p], S, dS, xbar, mass[p], mass[p] * v[p], mass[p] * C[p], stress, mls)
    scatter(gf, x[p], S, dS, xbar, mass[p], mass[p] * v[p], mass[p] * C[p], stress, mls)

@wp.kernel
def update(g: Grid, vel: wp.array3d(dtype=wp.vec3)):
    i, j, k = wp.tid()
    m = g.m[i, j, k]
    if m > 0.0:
        vel[i, j, k] = g.p[i, j, k] / m
    else:
        vel[i, j, k] = wp.vec3()

@wp.func
def gather(g: Grid, vel: wp.array3d(dtype=wp.vec3), x: wp.vec3, S: float, dS: wp.vec3, xbar: wp.vec3):
    base = base_of(g, x)
    v = wp.vec3(); B = wp.mat33(); D = wp.mat33(); G = wp.mat33()
    for i in range(3):
        for j in range(3):
            for k in range(3):
                r, gr = node_w(g, x, base, i, j, k)
                W = r / S
                gW = (gr - W * dS) / S
                I = base + wp.vec3i(i, j, k)
                vi = vel[I[0], I[1], I[2]]
                d = npos(g, base, i, j, k) - xbar
                v += W * vi
                B += W * wp.outer(vi, d)
                D += W * wp.outer(d, d)
                G += wp.outer(vi, gW)
    return v, B, D, G

@wp.kernel
def g2p(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
        F: wp.array(dtype=wp.mat33), gc: Grid, gf: Grid, vc: wp.array3d(dtype=wp.vec3),
        vf: wp.array3d(dtype=wp.vec3), dt: float, affine_grad: int, mixed: int):
    p = wp.tid()
    Sc, dSc, Xc = sums(gc, x[p])
    Sf, dSf, Xf = sums(gf, x[p])
    S = Sc + Sf
    dS = dSc + dSf
    xbar = (Xc + Xf) / S
    v1, B1, D1, G1 = gather(gc, vc, x[p], S, dS, xbar)
    v2, B2, D2, G2 = gather(gf, vf, x[p], S, dS, xbar)
    vp = v1 + v2
    G = G1 + G2
    if affine_grad != 0:
        C[p] = G
    else:
        C[p] = (B1 + B2) * wp.inverse(D1 + D2)
    if mixed != 0 and (Sc == 0.0 or Sf == 0.0):
        G = C[p]
    F[p] = (wp.identity(n=3, dtype=float) + dt * G) * F[p]
    v[p] = vp
    x[p] = x[p] + dt * vp

def lattice(lo, hi, h):
    axes = [np.arange(l + h / 2, u - 1e-9, h) for l, u in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)

def run(mode, b, dx=0.05, seconds=0.8, level_x=0.8, margin=0.0, width=1.0, affine_grad=0, frame=1/60, quiet=False, mixed=0):
    dxf = dx / b
    parts = []
    for lo, hi, vx in (((0.4, 0.35, 0.35), (0.8, 0.65, 0.65), 1.0), ((0.8, 0.35, 0.35), (1.2, 0.65, 0.65), -1.0)):
        # particles: fine where x >= level_x (or everywhere in finest), coarse elsewhere
        for sub_lo, sub_hi in ((lo, (min(hi[0], level_x),) + hi[1:]), ((max(lo[0], level_x),) + lo[1:], hi)):
            if sub_hi[0] <= sub_lo[0]:
                continue
            fine = mode == "finest" or (mode == "adaptive" and sub_lo[0] >= level_x)
            h = (dxf if fine else dx) / 2
            x = lattice(sub_lo, sub_hi, h)
            parts.append((x, np.full(len(x), h**3), np.tile([vx, 0, 0], (len(x), 1))))
    x = np.concatenate([q[0] for q in parts]); vol = np.concatenate([q[1] for q in parts])
    v = np.concatenate([q[2] for q in parts]); mass = RHO * vol
    nc = (int(1.6 / dx) + 3, int(1.0 / dx) + 3, int(1.0 / dx) + 3)
    nf = tuple(n * b for n in nc)
    def share_nodes(n, h, coarse):
        X = np.arange(n[0]) * h
        if mode == "original":
            a = np.ones(n[0])
        elif mode == "finest":
            a = np.zeros(n[0])
        else:  # coarse share: 1 left of level_x + margin, to 0 over width coarse cells
            a = np.clip(1.0 - (X - level_x - margin * dx) / (width * dx), 0.0, 1.0)
        s = a if coarse else 1.0 - a
        return np.broadcast_to(s[:, None, None], n).astype(np.float32).copy()
    grids, vels = [], []
    for n, h, coarse in ((nc, dx, True), (nf, dxf, False)):
        g = Grid(); g.dx = h; g.n = wp.vec3i(*n)
        g.share = wp.array(share_nodes(n, h, coarse), dtype=float)
        g.m = wp.zeros(n, dtype=float); g.p = wp.zeros(n, dtype=wp.vec3)
        grids.append(g); vels.append(wp.zeros(n, dtype=wp.vec3))
    X = wp.array(x, dtype=wp.vec3); V = wp.array(v, dtype=wp.vec3)
    Cm = wp.zeros(len(x), dtype=wp.mat33); Fm = wp.array(np.tile(np.eye(3), (len(x), 1, 1)), dtype=wp.mat33)
    M = wp.array(mass, dtype=float); VOL = wp.array(vol, dtype=float)
    cp = np.sqrt((LAM + 2 * MU) / RHO)
    dt = 0.3 * dxf / cp
    steps = int(round(seconds / dt)); every = max(1, int(round(frame / dt)))
    half = 0.5 * float((mass * np.abs(v[:, 0])).sum())
    ke, drift, t0 = [], 0.0, time.time()
    for s in range(steps):
        for g in grids:
            g.m.zero_(); g.p.zero_()
        wp.launch(p2g, len(x), inputs=[X, V, Cm, Fm, M, VOL, grids[0], grids[1], dt, mixed])
        for g, vg in zip(grids, vels):
            wp.launch(update, g.m.shape, inputs=[g, vg])
        wp.launch(g2p, len(x), inputs=[X, V, Cm, Fm, grids[0], grids[1], vels[0], vels[1], dt, affine_grad, mixed])
        vv = V.numpy().astype(np.float64)
        ke.append(0.5 * float((mass * (vv**2).sum(1)).sum()))
        drift = max(drift, float(np.linalg.norm((mass[:, None] * vv).sum(0))) / half)
        if not np.isfinite(ke[-1]) or np.abs(vv).max() > 50:
            return {"mode": mode, "unstable": s * dt, "drift": drift}
    ke = np.array(ke)
    peaks = [float(ke[i]) for i in range(1, len(ke) - 1) if ke[i] >= ke[i - 1] and ke[i] >= ke[i + 1] and ke[i] > 0.2 * ke[0]]
    xs = X.numpy()
    return {"mode": mode, "n": len(x), "drift": drift, "peaks": peaks[:6], "ke0": ke[0], "ke_end": ke[-1],
            "length": float(xs[:, 0].max() - xs[:, 0].min()), "wall": time.time() - t0, "steps": steps}

if __name__ == "__main__":
    b = int(sys.argv[1]) if len(sys.argv) > 1 else 2
    seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 0.8
    for mode, kw in [("original", {}), ("finest", {}), ("adaptive", dict(margin=0.0, width=1.0)),
                     ("adaptive", dict(margin=0.5, width=1.0)), ("adaptive", dict(margin=1.0, width=2.0))]:
        r = run(mode, b, seconds=seconds, **kw)
        print(mode, kw, {k: (round(v, 4) if isinstance(v, float) else ([round(q, 3) for q in v] if isinstance(v, list) else v)) for k, v in r.items()}, flush=True)
