"""What a particle's color costs near a collider (``abmpm bench --suite colliders``).

A particle within the collider band needs its color every step (closest surface
point, side, body: ``sim/colliders.py``). Two ways to get it, timed on the same
points in one run:

* ``bvh``: the BVH's closest-point query, bounded by the particle's distance plus
  its motion (what every band particle paid before ``sim/node_color.py``);
* ``lists``: the same query answered from the cell's list of triangles that can be
  closest (``sim/face_cells.py``, static colliders);
* ``nodes``: what G2P does now, the color read from the nodes' field where they
  vouch for it (``color_from_nodes``, then ``color_from_faces``), the lists' query
  elsewhere.

The points are sampled on the inside of a collider (area-weighted over its
triangles, 0.05 to 2.6 cells from the surface, the band's extent) so the figure
is per band particle and does not depend on how much material a scene happens to
have against its walls. The taken share and the largest distance difference
between the two answers are reported with the times.
"""

from __future__ import annotations

import time

import numpy as np
import trimesh
import warp as wp

from ..scene.loader import load_scene
from ..sim.collider_set import without_face_cells
from ..sim.colliders import PARTICLE_BAND, ColliderArrays, ColorField, color_point
from ..sim.grid import GridSpec
from ..sim.node_color import NEEDS_QUERY, color_from_faces, color_from_nodes
from ..simulation import Simulation

# cells: a band particle's motion in one CFL step (cfl 0.4 of a cell at the fastest
# particle; a typical one moves less): the bound of the BVH query is distance + this
MOTION = 0.2


@wp.kernel
def _band_colors(x: wp.array(dtype=wp.vec3), side: wp.array(dtype=wp.vec3), dist: wp.array(dtype=float),
                 colliders: ColliderArrays, g: GridSpec, f: ColorField, from_nodes: int,
                 body: wp.array(dtype=wp.int32), found: wp.array(dtype=float)):
    p = wp.tid()
    bound = wp.min(dist[p] + (MOTION + 0.01) * g.dx, PARTICLE_BAND * g.dx)
    body[p] = NEEDS_QUERY
    if from_nodes != 0:
        c = color_from_nodes(f, g, x[p], side[p], True)
        if c.body == NEEDS_QUERY:  # what G2P's query_color does first
            c = color_from_faces(f, g, colliders, x[p], side[p])
        body[p] = c.body
        found[p] = wp.length(x[p] - c.surface_point)
    if body[p] == NEEDS_QUERY:
        q = color_point(colliders, g, x[p], bound, side[p])
        found[p] = wp.length(x[p] - q.surface_point)
        if from_nodes == 0:
            body[p] = q.body


def band_points(sim: Simulation, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` points in the band on the side of each triangle facing the centre of
    the domain (the inside of a glass or a funnel), their side and their distance
    along the face normal."""
    rng = np.random.default_rng(seed)
    mesh = trimesh.util.concatenate(sim.colliders.body_meshes())
    on, face = trimesh.sample.sample_surface(mesh, count, seed=rng)  # area-weighted
    n = np.array(mesh.face_normals[face])
    centre = 0.5 * (np.asarray(sim.scene.simulation.domain_min) + np.asarray(sim.scene.simulation.domain_max))
    n[np.einsum("ij,ij->i", centre - on, n) < 0.0] *= -1.0
    dx = sim.solver.grid.spec.dx
    d = rng.uniform(0.05, PARTICLE_BAND, count) * dx
    # keep the points inside the domain
    x = np.clip(on + d[:, None] * n, sim.scene.simulation.domain_min, sim.scene.simulation.domain_max)
    return x.astype(np.float32), n.astype(np.float32), d.astype(np.float32)


def time_band_colors(scene_name: str = "paper_hourglass", count: int = 200_000, repeats: int = 5,
                     device: str = "cpu") -> dict:
    """ns per band particle of its color by the BVH, by the lists and from the nodes, on
    one thread (one ``wp.launch``), best of ``repeats``; the share the nodes vouched for."""
    sim = Simulation(load_scene(scene_name), device=device, mode="original")
    sim.step()  # colors the nodes
    grid = sim.solver.grid  # the coarse grid (original mode: the only one)
    x, n, d = band_points(sim, count)
    xs, ns, ds = (wp.array(a, dtype=t, device=device) for a, t in ((x, wp.vec3), (n, wp.vec3), (d, float)))
    body = wp.zeros(count, dtype=wp.int32, device=device)
    found = {name: wp.zeros(count, dtype=float, device=device) for name in ("bvh", "lists", "nodes")}
    out = {"scene": scene_name, "triangles": sim.colliders.triangle_count, "points": count,
           "lists_built": bool(sim.colliders.arrays.cells.enabled)}  # else "lists" is the BVH again
    listed = sim.colliders.arrays
    for mode, name, colliders in ((0, "bvh", without_face_cells(listed)), (0, "lists", listed), (1, "nodes", listed)):
        args = [xs, ns, ds, colliders, grid.spec, grid.color, mode, body, found[name]]
        wp.launch(_band_colors, count, args, device=device)
        wp.synchronize_device(device)
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            wp.launch(_band_colors, count, args, device=device)
            wp.synchronize_device(device)
            best = min(best, time.perf_counter() - t0)
        out[f"{name}_ns"] = round(1e9 * best / count, 1)
        if mode == 1:
            b = body.numpy()
            out["taken"] = round(float(np.mean(b != int(NEEDS_QUERY))), 3)

    def largest_difference(name: str) -> float:  # against the BVH's distance, in cells
        return float((np.abs(found["bvh"].numpy() - found[name].numpy()) / grid.spec.dx).max())

    out["largest_distance_difference_cells"] = round(largest_difference("nodes"), 4)
    out["lists_largest_difference_cells"] = round(largest_difference("lists"), 6)
    out["speedup"] = round(out["bvh_ns"] / out["nodes_ns"], 2)
    return out
