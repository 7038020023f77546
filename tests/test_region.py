"""Refined region B_s (abmpm.geometry.region): subdivision, kernel density, cells.

Reference readings of the density (module docstring of abmpm.geometry.region): one flat
wall 1.0, a sheet or a closed plate much thinner than h 2.0, the rim of a sheet 2.0.
Tolerances below state where they come from; "sampling" means the quadrature error
of area-weighted vertex samples with spacing <= h (measured <= ~1.5% on the
irregular quads that Catmull-Clark makes of a coarse mesh, ~0.01% on regular ones).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import trimesh
from scipy import ndimage

from abmpm.geometry import procedural as C
from abmpm.geometry.region import (
    RegionParams,
    cells_from_lambda,
    kde_density,
    kde_on_grid,
    refinement_region,
    surface_samples,
    triangle_samples,
)
from abmpm.geometry.subdivision import catmull_clark, densify
from abmpm.geometry.topology import boundary_loops, is_open

DX = 1.0 / 32.0
DIMS = (33, 33, 33)  # nodes; the grid spans [0, 1]^3


def node(i, j, k, dx=DX):
    return np.array([[i * dx, j * dx, k * dx]], dtype=np.float64)


# ----------------------------------------------------------------------------- Catmull-Clark


def _reference_cc(v, f):
    """Textbook Catmull-Clark of a closed manifold mesh, with loops (no creases)."""
    v = np.asarray(v, float)
    face_pt = np.array([v[list(face)].mean(0) for face in f])
    edge_faces = {}
    for fi, face in enumerate(f):
        for j in range(len(face)):
            a, b = sorted((face[j], face[(j + 1) % len(face)]))
            edge_faces.setdefault((a, b), []).append(fi)
    edge_pt = {e: (v[e[0]] + v[e[1]] + face_pt[fs[0]] + face_pt[fs[1]]) / 4 for e, fs in edge_faces.items()}
    vert_pt = np.empty_like(v)
    for i in range(len(v)):
        faces = [fi for fi, face in enumerate(f) if i in face]
        edges = [e for e in edge_faces if i in e]
        n = len(edges)
        F = face_pt[faces].mean(0)
        E = np.mean([(v[a] + v[b]) / 2 for a, b in edges], axis=0)
        vert_pt[i] = (F + 2 * E + (n - 3) * v[i]) / n  # Eq. 26
    return vert_pt, edge_pt, face_pt


def test_catmull_clark_cube_known_values():
    # quad cube [-1, 1]^3 without creases: corners go to +-5/9, edge points to 3/4
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    quads = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
    nv, fq = catmull_clark((v, quads), passes=1, crease_angle_deg=180.0)
    assert fq.shape == (24, 4)
    np.testing.assert_allclose(np.abs(nv[:8]), 5.0 / 9.0, atol=1e-12)
    edge_pts = nv[8:20]
    np.testing.assert_allclose(np.sort(np.abs(edge_pts), axis=1), np.tile([0.0, 0.75, 0.75], (12, 1)), atol=1e-12)
    np.testing.assert_allclose(np.sort(np.abs(nv[20:]), axis=1), np.tile([0.0, 0.0, 1.0], (6, 1)), atol=1e-12)


def test_catmull_clark_triangles_match_reference():
    mesh = trimesh.creation.icosphere(subdivisions=1)  # closed, valence 5 and 6
    nv, quads = catmull_clark(mesh, passes=1, crease_angle_deg=180.0)
    assert quads.shape == (3 * len(mesh.faces), 4)  # every triangle becomes 3 quads
    vert_pt, edge_pt, face_pt = _reference_cc(mesh.vertices, mesh.faces)
    n = len(mesh.vertices)
    np.testing.assert_allclose(nv[:n], vert_pt, atol=1e-12)
    np.testing.assert_allclose(nv[-len(face_pt):], face_pt, atol=1e-12)
    got = {tuple(np.round(p, 9)) for p in nv[n : len(nv) - len(face_pt)]}
    assert got == {tuple(np.round(p, 9)) for p in edge_pt.values()}
    assert mesh.vertices.shape == (42, 3)  # input untouched


def test_catmull_clark_keeps_boxes_and_sheet_corners():
    box = C.thin_box(size=(0.4, 0.05, 0.3))
    v, q = catmull_clark(box, passes=2)
    half = np.array([0.2, 0.025, 0.15])
    assert np.all(np.abs(v) <= half + 1e-12)
    # every vertex stays on the surface: some coordinate sits on a face plane
    assert np.all(np.any(np.isclose(np.abs(v), half, atol=1e-12), axis=1))
    np.testing.assert_allclose(v.min(0), -half, atol=1e-12)
    sheet = C.sheet(size=(1.0, 1.0))
    v, q = catmull_clark(sheet, passes=1)
    np.testing.assert_allclose(v[:, 1], 0.0, atol=1e-12)  # stays flat
    for corner in sheet.vertices:  # the four corners are kept
        assert np.min(np.linalg.norm(v - corner, axis=1)) < 1e-12


def test_catmull_clark_open_boundary_uses_curve_rule():
    # open disc (fan of a regular 24-gon): the rim vertices follow (a + 6 P + b) / 8
    m = 24
    t = 2 * np.pi * np.arange(m) / m
    v = np.concatenate([[[0.0, 0.0, 0.0]], np.stack([np.cos(t), np.zeros(m), np.sin(t)], 1)])
    f = np.stack([np.zeros(m, int), 1 + (np.arange(m) + 1) % m, 1 + np.arange(m)], 1)
    nv, _ = catmull_clark((v, f), passes=1)
    r = np.linalg.norm(nv[1 : m + 1], axis=1)
    np.testing.assert_allclose(r, (6 + 2 * np.cos(2 * np.pi / m)) / 8, atol=1e-12)


def test_densify_keeps_area_and_bounds_edges():
    mesh = C.letter_panel("AB", size=(0.6, 0.3))
    v, t = densify(mesh.vertices, mesh.faces, 0.01)
    lengths = np.linalg.norm(v[t] - v[np.roll(t, -1, axis=1)], axis=2)
    assert lengths.max() <= 0.01 + 1e-12
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1).sum()
    assert area == pytest.approx(mesh.area, rel=1e-12)


# ----------------------------------------------------------------------------- density


def test_grid_density_matches_kdtree():
    rng = np.random.default_rng(3)
    p = rng.uniform(-0.2, 1.2, size=(3000, 3))  # some far outside the grid
    w = rng.uniform(-0.5, 1.0, size=3000)
    h = 1.3 * DX
    dims = (17, 14, 19)
    origin = np.array([0.1, 0.2, 0.05])
    lam = kde_on_grid(p, w, origin, DX, dims, h)
    nodes = origin + DX * np.stack(np.meshgrid(*[np.arange(d) for d in dims], indexing="ij"), -1).reshape(-1, 3)
    ref = kde_density(p, w, nodes, h).reshape(dims)
    np.testing.assert_allclose(lam, ref, rtol=1e-10, atol=1e-12)


def test_thick_floor_reads_one_and_is_not_refined():
    floor = C.thin_box(size=(0.75, 0.25, 0.75), center=(0.5, 0.25, 0.5))  # top at node layer 12
    h = DX
    p, w = surface_samples(floor, h)
    centre = kde_density(p, w, node(16, 12, 16), h)[0]
    # 1.0 exactly for an infinite wall; 5% covers sampling (measured ~1%)
    assert centre == pytest.approx(1.0, rel=0.05)
    cells, lam = refinement_region([floor], [True], (0, 0, 0), DX, DIMS, RegionParams(halo=0, criterion="density"))
    assert not cells.any()
    # edges and corners read higher than the face (measured ~1.27 just inside them),
    # but stay under the default threshold
    assert lam.max() > centre + 0.15
    assert lam.max() < 1.5


def test_zero_thickness_sheet_reads_two_and_is_refined():
    sheet = C.sheet(size=(0.5, 0.5), center=(0.5, 0.5, 0.5))
    h = DX
    p, w = surface_samples(sheet, h)
    assert w.sum() > 2 * sheet.area  # counted twice, plus the rim line
    # 2.0 for an infinite sheet; 3% covers sampling
    assert kde_density(p, w, node(16, 16, 16), h)[0] == pytest.approx(2.0, rel=0.03)
    # the rim reads the sheet's value too (line term); 5% for sampling and the corner
    # quarter 4 h away
    assert kde_density(p, w, [[0.75, 0.5, 0.5]], h)[0] == pytest.approx(2.0, rel=0.05)
    cells, _ = refinement_region([sheet], [True], (0, 0, 0), DX, DIMS, RegionParams(halo=0, criterion="density"))
    assert cells[8:24, 15:17, 8:24].all()  # every cell the sheet touches
    assert not cells[:, :13, :].any() and not cells[:, 19:, :].any()


def test_thin_closed_plate_reads_two_and_is_refined():
    h = DX
    plate = C.thin_box(size=(0.5, 0.1 * h, 0.5), center=(0.5, 0.5, 0.5))
    assert not is_open(plate)
    p, w = surface_samples(plate, h)
    # two faces 0.05 h from the node: 2 exp(-0.05^2 / 2) = 1.9975; 3% for sampling
    assert kde_density(p, w, node(16, 16, 16), h)[0] == pytest.approx(2.0, rel=0.03)
    cells, _ = refinement_region([plate], [True], (0, 0, 0), DX, DIMS, RegionParams(criterion="density"))
    assert cells[9:23, 15:17, 9:23].all()


def test_open_flag_and_refine_flag():
    sheet = C.sheet(size=(0.5, 0.5), center=(0.5, 0.5, 0.5))
    h = DX
    p, w = surface_samples(sheet, h, open_surface=False)  # one-sided: reads like a wall
    assert kde_density(p, w, node(16, 16, 16), h)[0] == pytest.approx(1.0, rel=0.03)
    cells, lam = refinement_region([sheet], [False], (0, 0, 0), DX, DIMS)
    assert not cells.any() and not lam.any()
    cells, _ = refinement_region([sheet], [True], (0, 0, 0), DX, DIMS, RegionParams(criterion="density"),
                                 open_flags=[False])
    assert not cells.any()  # a one-sided surface is a wall, rims included


def test_tessellation_independence():
    h = DX
    coarse = C.sheet(size=(0.5, 0.5), center=(0.5, 0.5, 0.5))
    fine = C.sheet(size=(0.5, 0.5), center=(0.5, 0.5, 0.5), resolution=(37, 23))
    assert len(coarse.faces) == 2 and len(fine.faces) > 1000
    rng = np.random.default_rng(0)
    probes = np.column_stack([rng.uniform(0.35, 0.65, 20), 0.5 + rng.uniform(0, 1.5 * h, 20), rng.uniform(0.35, 0.65, 20)])
    probes[0] = (0.5, 0.5 + 0.5 * h, 0.5)  # above the middle
    a = kde_density(*surface_samples(coarse, h), probes, h)
    b = kde_density(*surface_samples(fine, h), probes, h)
    # 5%: sampling of either tessellation (measured < 1.5%)
    np.testing.assert_allclose(a, b, rtol=0.05)
    assert a[0] == pytest.approx(2.0 * np.exp(-0.125), rel=0.05)


def test_letter_panel_refined_around_every_hole_rim():
    dx = 1.0 / 64.0
    for shift in (0.0, 0.5 * dx):  # panel on a node layer, and halfway between two
        panel = C.letter_panel("ABC", size=(0.8, 0.4), center=(0.5, 0.5, 0.5 + shift))
        loops = boundary_loops(panel)
        assert len(loops) >= 6  # outline, 3 letters, inner islands
        cells, _ = refinement_region([panel], [True], (0, 0, 0), dx, (65, 65, 65), RegionParams(halo=0, criterion="density"))
        for loop in loops:
            ijk = np.floor(panel.vertices[loop] / dx).astype(int)
            assert cells[ijk[:, 0], ijk[:, 1], ijk[:, 2]].all()
        k = int(np.floor((0.5 + shift) / dx))
        assert not cells[:, :, : k - 3].any() and not cells[:, :, k + 4 :].any()


def test_hourglass_neck_refined_bulbs_not():
    dx = 1.0 / 64.0
    # a neck of radius r reads about sqrt(2 pi) (r/h) exp(-r^2/2h^2) on its axis, at
    # most 1.52 (r = h); 0.9 dx gives a margin of ~5% over the default threshold
    glass = C.hourglass(height=0.9, radius=0.3, neck_radius=0.9 * dx, wall_thickness=2.2 * dx, center=(0.5, 0.5, 0.5))
    p, w = surface_samples(glass, dx)
    assert kde_density(p, w, node(32, 32, 32, dx), dx)[0] > 1.5
    cells, _ = refinement_region([glass], [True], (0, 0, 0), dx, (65, 65, 65), RegionParams(halo=0, criterion="density"))
    assert cells[31:33, 31:33, 31:33].all()  # the cells around the axis at the neck
    # the wide part of both bulbs (y within 0.125-0.3 of the neck) is not refined:
    # a wall 2.2 h thick reads ~1.1 at most
    assert not cells[:, 8:20, :].any() and not cells[:, 45:57, :].any()


def test_explicit_boxes_add_cells():
    box = ((0.2, 0.1, 0.3), (0.4, 0.25, 0.5))
    cells, lam = refinement_region([], [], (0, 0, 0), DX, DIMS, RegionParams(boxes=[box], criterion="density"))
    centres = (np.arange(32) + 0.5) * DX
    expect = [((c >= lo) & (c <= hi)) for c, lo, hi in zip([centres] * 3, box[0], box[1])]
    want = expect[0][:, None, None] & expect[1][None, :, None] & expect[2][None, None, :]
    np.testing.assert_array_equal(cells, want)
    assert want.sum() == 7 * 5 * 6 and not lam.any()  # centres 6.5..12.5, 3.5..7.5, 10.5..15.5 dx
    sheet = C.sheet(size=(0.3, 0.3), center=(0.5, 0.8, 0.5))
    alone, _ = refinement_region([sheet], [True], (0, 0, 0), DX, DIMS, RegionParams(criterion="density"))
    both, _ = refinement_region([sheet], [True], (0, 0, 0), DX, DIMS, RegionParams(boxes=[box], criterion="density"))
    np.testing.assert_array_equal(both, alone | want)


def test_halo_grows_by_exactly_halo_cells():
    lam = np.zeros((20, 20, 20))
    lam[10, 10, 10] = 2.0  # one hot node: its 8 cells 9..10 per axis
    for halo in (0, 1, 2, 3):
        cells = cells_from_lambda(lam, 1.5, halo)
        idx = np.argwhere(cells)
        np.testing.assert_array_equal(idx.min(0), [9 - halo] * 3)
        np.testing.assert_array_equal(idx.max(0), [10 + halo] * 3)
        assert cells.sum() == (2 + 2 * halo) ** 3
    sheet = C.sheet(size=(0.4, 0.4), center=(0.5, 0.5, 0.5))
    c0, _ = refinement_region([sheet], [True], (0, 0, 0), DX, DIMS, RegionParams(halo=0, criterion="density"))
    c2, _ = refinement_region([sheet], [True], (0, 0, 0), DX, DIMS, RegionParams(halo=2, criterion="density"))
    np.testing.assert_array_equal(c2, ndimage.binary_dilation(c0, np.ones((3, 3, 3), bool), iterations=2))
    lo0, hi0 = np.argwhere(c0).min(0), np.argwhere(c0).max(0)
    lo2, hi2 = np.argwhere(c2).min(0), np.argwhere(c2).max(0)
    np.testing.assert_array_equal(lo2, lo0 - 2)
    np.testing.assert_array_equal(hi2, hi0 + 2)


def test_collision_mesh_unchanged_and_params_checked():
    sheet = C.sheet(size=(0.5, 0.5), center=(0.5, 0.5, 0.5))
    before = (sheet.vertices.copy(), sheet.faces.copy())
    refinement_region([sheet], [True], (0, 0, 0), DX, DIMS)
    np.testing.assert_array_equal(sheet.vertices, before[0])
    np.testing.assert_array_equal(sheet.faces, before[1])
    with pytest.raises(ValueError):
        RegionParams(bandwidth=0.0)
    with pytest.raises(ValueError):
        RegionParams(halo=-1)
    with pytest.raises(ValueError):
        RegionParams(boxes=[((1, 1, 1), (0, 0, 0))])
    with pytest.raises(ValueError):
        refinement_region([sheet], [True, False], (0, 0, 0), DX, DIMS)


def test_grid_density_speed():
    # ~40k samples (the vertices of a fine sphere) on a 65^3 grid: ~0.3 s on one free
    # core; the bound is loose for shared CI machines and only catches an accidental
    # quadratic path
    sphere = trimesh.creation.icosphere(subdivisions=6, radius=0.3)
    sphere.apply_translation((0.5, 0.5, 0.5))
    p, w = triangle_samples(sphere.vertices, sphere.faces, max_edge=1.0)  # no splitting
    assert len(p) == 40962
    dx = 1.0 / 64.0
    t0 = time.perf_counter()
    lam = kde_on_grid(p, w, (0, 0, 0), dx, (65, 65, 65), dx)
    elapsed = time.perf_counter() - t0
    assert elapsed < 5.0
    # a sphere of radius 19 h reads ~1 on its surface; 5% for its curvature and
    # for nodes lying up to half a cell off the surface (exp(-1/8) = 0.88 at worst)
    on_surface = np.abs(np.linalg.norm(np.argwhere(np.ones(lam.shape, bool)) * dx - 0.5, axis=1) - 0.3) < 0.1 * dx
    assert on_surface.sum() > 50
    np.testing.assert_allclose(lam.reshape(-1)[on_surface], 1.0, rtol=0.05)


# ----------------------------------------------------------------------------- feature size
#
# criterion = "feature" (the default): cells are refined around free space narrower than
# gap_cells (3) coarse cells and around the edges of moving colliders, then grown by the
# halo (1). The grid is [0, 1]^3 with walls on its faces; DX = 1/32.

WALLS = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))


def feature(meshes, halo=1, moving=None, **kw):
    cells, _ = refinement_region(meshes, [True] * len(meshes), (0, 0, 0), DX, DIMS,
                                 RegionParams(**{"halo": halo, "walls": WALLS, **kw}), moving_flags=moving)
    return cells


def cell_centres(cells):
    return (np.argwhere(cells) + 0.5) * DX


def sheet_with_hole(radius, y=0.5 + 0.3 * DX):
    """A sheet spanning the domain at height y with a round hole at (0.5, 0.5)."""
    import shapely.geometry as sg

    poly = sg.box(0, 0, 1, 1).difference(sg.Point(0.5, 0.5).buffer(radius, 32))
    v2, f = trimesh.creation.triangulate_polygon(poly)
    v = np.column_stack([v2[:, 0], np.full(len(v2), y), v2[:, 1]])
    return trimesh.Trimesh(v, f, process=False)


def test_feature_flat_sheet_spanning_the_domain_is_not_refined():
    # free on both sides, its rim touches the walls (a contact, not a gap): nothing at
    # all; the density criterion refines it everywhere
    sheet = C.sheet(size=(1.0, 1.0), center=(0.5, 0.5 + 0.3 * DX, 0.5))
    assert not feature([sheet]).any()
    assert feature([sheet], criterion="density").sum() >= 32 * 32 * 2
    # a free-floating sheet and a thin closed plate: nothing either
    assert not feature([C.sheet(size=(0.5, 0.5), center=(0.5, 0.5, 0.5))]).any()
    assert not feature([C.thin_box(size=(0.5, 0.1 * DX, 0.5), center=(0.5, 0.5, 0.5))]).any()
    # "both" is the union: the density's cells
    both = feature([sheet], criterion="both")
    np.testing.assert_array_equal(both, feature([sheet], criterion="density"))


def test_feature_sheet_refined_around_its_small_hole_only():
    r = 1.2 * DX  # a hole 2.4 coarse cells across
    cells = feature([sheet_with_hole(r)])
    assert cells.any()
    c = cell_centres(cells)
    # every refined cell lies within the hole's radius + halo + one cell of its axis
    # (the marks are the rim, the middle and the far side of each narrow width)
    dist = np.hypot(c[:, 0] - 0.5, c[:, 2] - 0.5)
    assert dist.max() < r + 2.5 * DX
    assert np.abs(c[:, 1] - 0.5).max() < 2.5 * DX
    # the hole's cells (4 x 4 columns around the axis, both sides of the sheet) are in
    assert cells[15:17, 15:17, 15:17].all()
    assert cells.sum() <= 8 * 6 * 8  # a few cells around the hole, of 32^2 x 2 the sheet touches
    # a hole 10 cells across is wide: not refined (corners of the hole do not exist on a circle)
    assert not feature([sheet_with_hole(5 * DX)]).any()


def test_feature_slit_between_two_plates_refined_plates_not():
    for slit in (0.5 * DX, 1.5 * DX):
        half = (1.0 - slit) / 2
        for make in (lambda s, c: C.sheet(size=s, center=c),
                     lambda s, c: C.thin_box(size=(s[0], 0.004, s[1]), center=c)):
            plates = [make((half, 1.0), (half / 2, 0.5, 0.5)), make((half, 1.0), (1 - half / 2, 0.5, 0.5))]
            cells = feature(plates)
            c = cell_centres(cells)
            # the slit's columns (x within the slit +- 1 cell, y at the plates), all z
            assert cells[15:17, 15:17, :].all()
            # nothing further than slit/2 + halo + 1 cell from the slit's middle
            assert np.abs(c[:, 0] - 0.5).max() < slit / 2 + 2.5 * DX
            assert np.abs(c[:, 1] - 0.5).max() < 2.5 * DX


def test_feature_of_a_finely_meshed_slit_is_the_coarse_meshes():
    """Plates meshed 50k triangles each mark the cells two triangles each do: the samples
    are thinned to the criterion's own spacing before widths are measured (without that a
    sheet of a million triangles paired every sample with thousands and filled the
    memory)."""
    slit, half = 0.75 * DX, (1.0 - 0.75 * DX) / 2
    centres = ((half / 2, 0.5, 0.5), (1 - half / 2, 0.5, 0.5))
    coarse = [C.sheet(size=(half, 1.0), center=c) for c in centres]
    fine = [C.sheet(size=(half, 1.0), center=c, resolution=(160, 160)) for c in centres]
    assert len(fine[0].faces) > 50_000
    np.testing.assert_array_equal(feature(fine), feature(coarse))


def test_feature_wide_gap_not_refined_narrow_parallel_gap_refined():
    g = 10 * DX
    half = (1.0 - g) / 2
    plates = [C.sheet(size=(half, 1.0), center=(half / 2, 0.5, 0.5)),
              C.sheet(size=(half, 1.0), center=(1 - half / 2, 0.5, 0.5))]
    assert not feature(plates).any()
    far = [C.sheet(size=(0.6, 0.6), center=(0.5, 0.3, 0.5)), C.sheet(size=(0.6, 0.6), center=(0.5, 0.3 + g, 0.5))]
    assert not feature(far).any()
    near = [C.sheet(size=(0.6, 0.6), center=(0.5, 0.5, 0.5)), C.sheet(size=(0.6, 0.6), center=(0.5, 0.5 + 2 * DX, 0.5))]
    cells = feature(near)
    assert cells[12:20, 16:18, 12:20].all()  # between the two sheets
    # a sheet 2 cells above the floor (a wall): the gap below it is refined
    low = feature([C.sheet(size=(0.6, 0.6), center=(0.5, 2 * DX + 0.3 * DX, 0.5))])
    assert low[12:20, 0:2, 12:20].all() and not low[:, 5:, :].any()
    assert not feature([C.sheet(size=(0.6, 0.6), center=(0.5, 2 * DX + 0.3 * DX, 0.5))], walls=None).any()


def test_feature_hourglass_neck_refined_bulbs_not():
    # neck radius ~1 coarse cell: the width across it (2 cells) is narrow; the bulbs
    # (up to 0.6 m across, 6 cells from the walls at their widest) are not. Outside,
    # the waist is a concave wedge (~96 degrees) between the two cones, narrow within
    # ~3 cells of its apex ring: that ring is refined too (radius < 7 cells)
    glass = C.hourglass(height=0.6, radius=0.3, neck_radius=1.0 * DX, center=(0.5, 0.5, 0.5))
    cells = feature([glass])
    assert cells[15:17, 15:17, 15:17].all()  # the neck
    c = cell_centres(cells)
    assert np.abs(c[:, 1] - 0.5).max() < 6 * DX  # the neck +- a few cells, not the bulbs
    assert np.hypot(c[:, 0] - 0.5, c[:, 2] - 0.5).max() < 7 * DX
    assert cells.sum() < 0.02 * cells.size


def test_feature_moving_blade_edges_refined():
    blade = C.thin_box(size=(0.4, 0.3, 0.1 * DX), center=(0.5, 0.5, 0.5 + 0.3 * DX))
    assert not feature([blade]).any()  # static: a thin plate in free space
    cells = feature([blade], halo=0, moving=[True])
    c = cell_centres(cells)
    # the cells along its 12 edges (the rims of the 0.4 x 0.3 faces): the middle of
    # the faces stays coarse
    assert cells.any() and not cells[12:20, 13:19, :].any()
    d_edge = np.minimum(np.abs(np.abs(c[:, 0] - 0.5) - 0.2), np.abs(np.abs(c[:, 1] - 0.5) - 0.15))
    assert d_edge.max() < DX


def test_feature_criterion_checked_and_scene_default():
    from abmpm.scene.model import Refinement

    with pytest.raises(ValueError):
        RegionParams(criterion="nope")
    with pytest.raises(ValueError):
        RegionParams(gap_cells=0.0)
    assert RegionParams().criterion == "feature" and Refinement().criterion == "feature"
    assert Refinement().gap_cells == 3.0
