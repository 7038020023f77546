"""An outside check of docs/method.md, "Outcomes at a sheet depend on the step": the
smallest MLS-MPM we could write (APIC or PIC, quadratic B-splines, 8 jittered particles a
cell, a weakly compressible fluid, explicit steps), none of abmpm's code. Water (K = 2e4
Pa) falls 0.04 m on to a plate that spans the box, made of one layer of grid nodes whose
normal velocity is zeroed (the plain MPM boundary condition, no CPIC), with a round hole
as the only way down: the interface matrix's plate case. Prints the fraction of the mass
below the plate at 0.5 s.

    python docs/prototypes/minimal_hole_drain.py CFL HOLE_CELLS B [pic | flip=F]

(HOLE_CELLS coarse cells of 0.04 m across, on a grid of 0.04 / B m.) Measured
2026-11-27 (night), hole 2 cells, B = 3 (the grid of the matrix's finest mode): APIC 0.161 /
0.131 / 0.102 / 0.070 at CFL 0.4 / 0.2 / 0.1 / 0.05 (654 / 1,284 / 2,494 / 4,727 steps);
PIC 0.085 / 0.024 at 0.4 / 0.1. With a FLIP share F of the particle's own velocity kept
(v_p = grid + F (v_p - the grid's old velocity at x_p), APIC's C as before; 2026-11-28):
F = 0.9 0.233 / 0.204 / 0.173 / 0.140, F = 0.99 0.407 / 0.412 / 0.338 / 0.517 (noisy) at CFL 0.4 /
0.2 / 0.1 / 0.05: the drain still depends on the step."""
import sys, numpy as np, warp as wp
wp.config.quiet = True
wp.init()
cfl = float(sys.argv[1]); hole_cells = float(sys.argv[2]); b = int(sys.argv[3])
pic = len(sys.argv) > 4 and sys.argv[4] == "pic"
flip = float(sys.argv[4][5:]) if len(sys.argv) > 4 and sys.argv[4].startswith("flip=") else 0.0
W, H, Z = 0.4, 0.5, 0.16
dx = 0.04 / b
G = (int(round(W / dx)) + 1, int(round(H / dx)) + 1, int(round(Z / dx)) + 1)
HI = wp.vec3(W - dx, H - dx, Z - dx)
rho, K, grav = 1000.0, 2e4, 9.81
c = (K / rho) ** 0.5
plate_j = int(round(0.2 / dx))
R = 0.5 * hole_cells * 0.04
rng = np.random.default_rng(0)
# 8 particles per cell, jittered
g = np.stack(np.meshgrid(*[np.arange(a, bb, dx / 2) + dx / 4 for a, bb in ((0, W), (0.24, 0.44), (0, Z))], indexing="ij"), -1).reshape(-1, 3)
g += (rng.random(g.shape) - 0.5) * dx / 4
n = len(g); vol = (dx / 2) ** 3; mass = rho * vol

@wp.func
def stencil(xp: wp.vec3, dx: float):
    # the quadratic B-spline stencil: lowest node, offset from it in cells, weights (rows: nodes)
    Xp = xp / dx
    base = wp.vec3i(int(Xp[0] - 0.5), int(Xp[1] - 0.5), int(Xp[2] - 0.5))
    fx = Xp - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    a = wp.vec3(1.5) - fx
    bb = fx - wp.vec3(1.0)
    cc = fx - wp.vec3(0.5)
    return base, fx, wp.matrix_from_rows(0.5 * wp.cw_mul(a, a), wp.vec3(0.75) - wp.cw_mul(bb, bb), 0.5 * wp.cw_mul(cc, cc))


@wp.kernel
def p2g(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33), J: wp.array(dtype=float),
        gv: wp.array3d(dtype=wp.vec3), gm: wp.array3d(dtype=float), dx: float, dt: float, vol: float, mass: float, K: float):
    p = wp.tid()
    base, fx, w = stencil(x[p], dx)
    pr = K * (1.0 / J[p] - 1.0)
    stress = -dt * 4.0 / (dx * dx) * vol * J[p] * (-pr)
    affine = wp.identity(n=3, dtype=float) * stress + mass * C[p]
    for i in range(3):
        for j in range(3):
            for k in range(3):
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                weight = w[i, 0] * w[j, 1] * w[k, 2]
                wp.atomic_add(gv, base[0] + i, base[1] + j, base[2] + k, weight * (mass * v[p] + affine * dpos))
                wp.atomic_add(gm, base[0] + i, base[1] + j, base[2] + k, weight * mass)

@wp.kernel
def update(gv: wp.array3d(dtype=wp.vec3), v0: wp.array3d(dtype=wp.vec3), gm: wp.array3d(dtype=float), dt: float,
           g: float, dx: float,
           pj: int, R: float, cx: float, cz: float, nx: int, ny: int, nz: int):
    i, j, k = wp.tid()
    m = gm[i, j, k]
    if m > 0.0:
        v0[i, j, k] = gv[i, j, k] / m  # the velocity P2G gave the node (FLIP's old grid velocity)
        vv = gv[i, j, k] / m - wp.vec3(0.0, dt * g, 0.0)
        # slip walls on the box
        if i <= 1 and vv[0] < 0.0: vv[0] = 0.0
        if i >= nx - 3 and vv[0] > 0.0: vv[0] = 0.0
        if j >= ny - 3 and vv[1] > 0.0: vv[1] = 0.0
        if j <= 1 and vv[1] < 0.0: vv[1] = 0.0
        if k <= 1 and vv[2] < 0.0: vv[2] = 0.0
        if k >= nz - 3 and vv[2] > 0.0: vv[2] = 0.0
        # the plate: one node layer, slip, no normal motion, except in the hole
        if j == pj:
            ddx = float(i) * dx - cx
            ddz = float(k) * dx - cz
            if ddx * ddx + ddz * ddz > R * R:
                vv[1] = 0.0
        gv[i, j, k] = vv
    else:
        gv[i, j, k] = wp.vec3(0.0)
        v0[i, j, k] = wp.vec3(0.0)

@wp.kernel
def g2p(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33), J: wp.array(dtype=float),
        gv: wp.array3d(dtype=wp.vec3), v0: wp.array3d(dtype=wp.vec3), flip: float, dx: float, dt: float, pic: int,
        speed: wp.array(dtype=float), hi: wp.vec3):
    p = wp.tid()
    base, fx, w = stencil(x[p], dx)
    nv = wp.vec3(0.0); nC = wp.mat33(0.0); ov = wp.vec3(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                weight = w[i, 0] * w[j, 1] * w[k, 2]
                gvv = gv[base[0] + i, base[1] + j, base[2] + k]
                nv += weight * gvv
                ov += weight * v0[base[0] + i, base[1] + j, base[2] + k]
                nC += (4.0 / (dx * dx) * weight) * wp.outer(gvv, dpos)
    J[p] = J[p] * (1.0 + dt * wp.trace(nC))
    xn = x[p] + dt * nv
    nv = nv + flip * (v[p] - ov)
    v[p] = nv
    if pic == 0:
        C[p] = nC
    lo = 1.0 * dx
    xn = wp.vec3(wp.clamp(xn[0], lo, hi[0]), wp.clamp(xn[1], lo, hi[1]), wp.clamp(xn[2], lo, hi[2]))
    x[p] = xn
    wp.atomic_max(speed, 0, wp.length(nv))

x = wp.array(g.astype(np.float32), dtype=wp.vec3); v = wp.zeros(n, dtype=wp.vec3); C = wp.zeros(n, dtype=wp.mat33)
J = wp.ones(n, dtype=float)
GP = tuple(a + 3 for a in G)
gv = wp.zeros(GP, dtype=wp.vec3); v0 = wp.zeros(GP, dtype=wp.vec3); gm = wp.zeros(GP, dtype=float)
speed = wp.zeros(1, dtype=float)
t, steps, vmax = 0.0, 0, 0.0
while t < 0.5 - 1e-9:
    dt = min(2e-3, cfl * dx / (c + vmax), 0.5 - t)
    gv.zero_(); gm.zero_(); speed.zero_()
    wp.launch(p2g, n, [x, v, C, J, gv, gm, dx, dt, vol, mass, K])
    wp.launch(update, GP, [gv, v0, gm, dt, grav, dx, plate_j, R, W / 2, Z / 2, G[0], G[1], G[2]])
    wp.launch(g2p, n, [x, v, C, J, gv, v0, flip, dx, dt, int(pic), speed, HI])
    vmax = float(speed.numpy()[0]); t += dt; steps += 1
xs = x.numpy()
print(f"cfl {cfl} hole {hole_cells} b {b} pic {pic} flip {flip}: through {np.mean(xs[:,1] < 0.2 - 0.5*dx):.4f} steps {steps}", flush=True)
