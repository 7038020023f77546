"""The per-cell lists of the triangles that can be closest (sim/face_cells.py) against
the BVH's closest-point query they stand in for: the same answer at every point of the
band, on both sides of a curved glass and next to the rims of a perforated plate."""

from __future__ import annotations

import numpy as np
import trimesh
import warp as wp

from abmpm.scene import model as sm
from abmpm.sim.colliders import PARTICLE_BAND, ColliderArrays, color_point
from abmpm.sim.collider_set import without_face_cells
from abmpm.sim.face_cells import build_face_cells, face_discs
from abmpm.sim.grid import GridSpec
from abmpm.simulation import Simulation

# Warp's BVH and the lists' closest point on a triangle (Ericson's) are two float32
# evaluations of the same point: measured 1.2e-5 cells apart at most on the paper
# hourglass (positions ~0.5 m carry ~3e-8 m of round-off, 1e-6 of a cell, and the
# projections add a few ulps more). 1e-4 cells is an order above that and far below any
# real difference (another triangle of the glass is 0.01 cells or more off).
DIST_TOL = 1.0e-4
# a point within this of its bound (cells) may be found by one query and not the other
# (the bound is compared with two roundings of one distance)
BOUND_TOL = 1.0e-4


@wp.kernel
def compare_queries(x: wp.array(dtype=wp.vec3), bound: wp.array(dtype=float), side: wp.array(dtype=wp.vec3),
                    listed: ColliderArrays, bvh: ColliderArrays, g: GridSpec,
                    found: wp.array(dtype=wp.vec2i), dist: wp.array(dtype=wp.vec2), same_body: wp.array(dtype=wp.int32)):
    p = wp.tid()
    a = color_point(listed, g, x[p], bound[p], side[p])
    b = color_point(bvh, g, x[p], bound[p], side[p])
    found[p] = wp.vec2i(a.body, b.body)
    dist[p] = wp.vec2(wp.length(x[p] - a.surface_point), wp.length(x[p] - b.surface_point)) / g.dx
    same_body[p] = int(a.body == b.body)


def glass_and_sheet() -> sm.Scene:
    """A tilted hourglass (curved, both sides in reach) above a tilted sheet (rims)."""
    glass = sm.HourglassCollider(height=0.5, radius=0.15, neck_radius=0.04, center=(0.3, 0.36, 0.3),
                                 rotation=(12.0, 0.0, 7.0))
    plate = sm.SheetCollider(size=(0.4, 0.4), center=(0.3, 0.07, 0.3), resolution=17, rotation=(5.0, 0.0, -9.0))
    return sm.Scene(simulation=sm.SimulationSettings(dx=0.01, domain_min=(0.0, 0.0, 0.0), domain_max=(0.6, 0.66, 0.6)),
                    materials=[sm.Fluid(name="water")],
                    bodies=[sm.SphereBody(material="water", center=(0.3, 0.45, 0.3), radius=0.05)],
                    colliders=[glass, plate])


def band_samples(sim: Simulation, count: int, seed: int = 0):
    """Points on both sides of every collider, from on the surface to beyond the band,
    with random query bounds up to the band and the side they came from."""
    rng = np.random.default_rng(seed)
    mesh = trimesh.util.concatenate(sim.colliders.body_meshes())
    on, face = trimesh.sample.sample_surface(mesh, count, seed=rng)
    n = np.array(mesh.face_normals[face]) * rng.choice([-1.0, 1.0], count)[:, None]
    dx = sim.solver.grids[0].spec.dx
    x = on + rng.uniform(0.02, 1.2 * PARTICLE_BAND, count)[:, None] * dx * n
    bound = rng.uniform(0.2, PARTICLE_BAND, count) * dx
    return x.astype(np.float32), bound.astype(np.float32), n.astype(np.float32)


def test_the_lists_answer_what_the_bvh_answers():
    sim = Simulation(glass_and_sheet(), device="cpu", mode="original")
    arrays = sim.colliders.arrays
    assert arrays.cells.enabled == 1, "static colliders in CPIC mode get their lists"
    x, bound, side = band_samples(sim, 40_000)
    g = sim.solver.grids[0].spec
    n = len(x)
    found = wp.zeros(n, dtype=wp.vec2i)
    dist = wp.zeros(n, dtype=wp.vec2)
    same = wp.zeros(n, dtype=wp.int32)
    wp.launch(compare_queries, n, [wp.array(x, dtype=wp.vec3), wp.array(bound, dtype=float), wp.array(side, dtype=wp.vec3),
                                   arrays, without_face_cells(arrays), g, found, dist, same])
    f, d = found.numpy(), dist.numpy()
    hit = f >= 0
    # points whose closest surface lies at their bound are left out (see BOUND_TOL)
    at_bound = np.abs(np.where(hit[:, 1], d[:, 1], np.inf) - bound / g.dx) < BOUND_TOL
    at_bound |= np.abs(np.where(hit[:, 0], d[:, 0], np.inf) - bound / g.dx) < BOUND_TOL
    keep = ~at_bound
    assert keep.sum() > 0.99 * n
    assert np.array_equal(hit[keep, 0], hit[keep, 1]), "found by one query and not by the other"
    both = keep & hit[:, 0]
    assert both.sum() > 0.3 * n  # a good share of the points have a surface within their bound
    assert np.abs(d[both, 0] - d[both, 1]).max() < DIST_TOL
    assert same.numpy()[both].all(), "the same collider"


def test_the_lists_give_way_to_the_bvh_where_they_would_not_pay():
    # moving colliders keep the BVH alone; so do lists over the memory limit, and lists
    # of a mesh much finer than the grid (a 20k-triangle ball of 0.15 m on 5 cm cells:
    # hundreds of triangles a cell, slower to scan than the BVH's traversal)
    scene = glass_and_sheet()
    moving = scene.colliders[0].model_copy(update={"motion": sm.Motion(velocity=(0.1, 0.0, 0.0))})
    sim = Simulation(scene.model_copy(update={"colliders": [moving, scene.colliders[1]]}), device="cpu",
                     mode="original")
    assert sim.colliders.arrays.cells.enabled == 0
    grid = sim.solver.grids[0]
    cells = [int(c) - 1 for c in grid.dims]
    small = build_face_cells(sim.colliders.mesh, grid.origin, grid.dx, cells, PARTICLE_BAND * grid.dx,
                             sim.solver.launcher, max_entries=1000)
    assert small.enabled == 0
    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.15)
    mesh = wp.Mesh(points=wp.array((ball.vertices + 0.3).astype(np.float32), dtype=wp.vec3),
                   indices=wp.array(ball.faces.astype(np.int32).ravel(), dtype=wp.int32))
    fine = build_face_cells(mesh, (0.0, 0.0, 0.0), 0.05, (12, 12, 12), PARTICLE_BAND * 0.05, sim.solver.launcher)
    assert fine.enabled == 0
    coarse = build_face_cells(mesh, (0.0, 0.0, 0.0), 0.005, (120, 120, 120), PARTICLE_BAND * 0.005, sim.solver.launcher)
    assert coarse.enabled == 1  # the same ball on cells about its triangles' size
    # a collider wholly outside the grid: no cell to list, no error
    away = wp.Mesh(points=wp.array((ball.vertices + 5.0).astype(np.float32), dtype=wp.vec3),
                   indices=wp.array(ball.faces.astype(np.int32).ravel(), dtype=wp.int32))
    assert build_face_cells(away, (0.0, 0.0, 0.0), 0.05, (12, 12, 12), PARTICLE_BAND * 0.05, sim.solver.launcher).enabled == 0


@wp.kernel
def disc_bounds(x: wp.array(dtype=wp.vec3), disc: wp.array(dtype=wp.vec4), normal: wp.array(dtype=wp.vec3),
                out: wp.array(dtype=float)):
    p = wp.tid()
    w = x[p] - wp.vec3(disc[p][0], disc[p][1], disc[p][2])
    h = wp.dot(w, normal[p])
    r = wp.max(wp.sqrt(wp.max(wp.dot(w, w) - h * h, 0.0)) - disc[p][3], 0.0)
    out[p] = wp.sqrt(h * h + r * r)


def test_a_triangles_disc_is_never_farther_than_the_triangle():
    # the scan passes over a triangle whose disc is at least the best distance away, so the
    # disc's distance must bound the triangle's from below: random slivers, needles, a
    # degenerate (collinear) triangle, points on every side and in the plane
    rng = np.random.default_rng(3)
    n = 20_000
    tri = rng.normal(size=(n, 3, 3)) * rng.uniform(0.001, 0.1, (n, 1, 1))
    tri[::7, 2] = tri[::7, 0] + 0.37 * (tri[::7, 1] - tri[::7, 0])  # collinear: no plane
    tri[::5, 2] = tri[::5, 1] + 1e-4 * (tri[::5, 2] - tri[::5, 1])  # needles
    x = tri.mean(axis=1) + rng.normal(size=(n, 3)) * rng.uniform(0.0, 0.2, (n, 1))
    disc, normal = face_discs(tri.reshape(-1, 3), np.arange(3 * n))
    out = wp.zeros(n, dtype=float)
    wp.launch(disc_bounds, n, [wp.array(x.astype(np.float32), dtype=wp.vec3), wp.array(disc, dtype=wp.vec4),
                               wp.array(normal, dtype=wp.vec3), out])
    exact = trimesh.triangles.closest_point(tri, x)
    true = np.linalg.norm(exact - x, axis=1)
    bound = out.numpy()
    # float32 evaluation of the bound, ~1e-7 of the scale (0.1 m): the scan's DISC_SLACK
    # allows 1e-4 of a cell (~1e-6 m at the smallest cells of the suite)
    assert np.all(bound <= true + 1e-6)
    assert np.mean(bound > 0.5 * true) > 0.5  # and it is a useful bound, not zero
