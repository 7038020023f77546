"""Boundary responses shared by domain walls and rigid colliders."""

from __future__ import annotations

import warp as wp

BOUNDARY_STICKY = wp.constant(0)
BOUNDARY_SLIP = wp.constant(1)
BOUNDARY_SEPARATE = wp.constant(2)
BOUNDARY_IDS = {"sticky": 0, "slip": 1, "separate": 2}
# the six faces of the box domain, in the order the solver stores their walls
FACES = ("x_min", "x_max", "y_min", "y_max", "z_min", "z_max")


@wp.func
def boundary_response(v: wp.vec3, v_r: wp.vec3, n: wp.vec3, boundary: int, friction: float, separation: float):
    """Velocity after contact with a boundary moving at v_r, normal n (into the material).

    Sticky: the boundary's velocity. Slip: no relative normal motion either way.
    Separate: approaching normal motion removed, leaving is free. Slip and separate
    lose tangential speed to Coulomb friction mu |v_n| (never reversing it) and add
    the separating speed c n of paper Eq. 23.
    """
    if boundary == BOUNDARY_STICKY:
        return v_r
    v_rel = v - v_r
    vn = wp.dot(v_rel, n)
    if vn >= 0.0 and boundary == BOUNDARY_SEPARATE:
        return v
    vt = v_rel - vn * n
    if vn < 0.0 and friction > 0.0:
        vt_len = wp.length(vt)
        if vt_len > 0.0:
            vt = vt * wp.max(0.0, 1.0 - friction * (-vn) / vt_len)
    return v_r + vt + separation * n
