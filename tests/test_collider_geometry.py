"""Procedural collider geometry (abmpm.geometry.procedural, glyphs, topology)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from abmpm.geometry.glyphs import letter_hole_polygons
from abmpm.geometry.collider_shapes import REGISTRY as SHAPES
from abmpm.geometry.procedural import (
    blade,
    crossed_plates,
    funnel,
    hourglass,
    letter_panel,
    paddle,
    sheet,
    thin_box,
)
from abmpm.geometry.topology import boundary_loops, is_open, mesh_boundary_edges
from abmpm.geometry.transforms import euler_matrix

CLOSED = {
    "thin_box": lambda: thin_box((0.5, 0.002, 0.3), (0.1, 0.2, 0.3), (10, 20, 30)),
    "blade_thick": lambda: blade(0.4, 0.2, 0.002),
    "crossed_thick": lambda: crossed_plates((0.4, 0.3), 0.004),
    "letter_thick": lambda: letter_panel("LOB", (0.6, 0.3), 0.004),
    "hourglass_wall": lambda: hourglass(0.5, 0.15, 0.02, wall_thickness=0.004, segments=32),
}

OPEN = {
    "sheet": lambda: sheet((0.5, 0.3), resolution=(4, 3)),
    "blade": lambda: blade(0.4, 0.2),
    "paddle": lambda: paddle(0.4, 0.2, (0.5, 0.5, 0.5)),
    "crossed": lambda: crossed_plates((0.4, 0.3)),
    "funnel": lambda: funnel(0.2, 0.03, 0.15, 0.1, segments=32),
    "hourglass": lambda: hourglass(0.5, 0.15, 0.02, segments=32),
    "letter": lambda: letter_panel("LOB", (0.6, 0.3)),
}


def edge_use_counts(mesh: trimesh.Trimesh) -> np.ndarray:
    _, counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    return counts


def assert_clean(mesh: trimesh.Trimesh) -> None:
    assert isinstance(mesh, trimesh.Trimesh)
    assert mesh.vertices.dtype == np.float64
    assert len(mesh.faces) > 0 and np.all(np.isfinite(mesh.vertices))
    assert mesh.nondegenerate_faces(height=1e-10).all(), "degenerate (zero-area) faces"
    assert edge_use_counts(mesh).max() <= 2, "an edge is shared by more than two faces"
    assert mesh.is_winding_consistent


@pytest.mark.parametrize("name", sorted(CLOSED))
def test_closed_colliders_are_watertight_solids(name):
    mesh = CLOSED[name]()
    assert_clean(mesh)
    assert mesh.is_watertight and mesh.is_volume
    assert not is_open(mesh) and mesh_boundary_edges(mesh).shape == (0, 2)
    assert mesh.volume > 0.0  # outward normals


@pytest.mark.parametrize("name", sorted(OPEN))
def test_open_colliders_have_boundary_and_no_degenerate_faces(name):
    mesh = OPEN[name]()
    assert_clean(mesh)
    edges = mesh_boundary_edges(mesh)
    assert is_open(mesh) and not mesh.is_watertight
    assert edges.ndim == 2 and edges.shape[1] == 2 and len(edges) > 0
    assert np.issubdtype(edges.dtype, np.integer)


def test_registry_names_builders():
    assert set(SHAPES) >= {"sheet", "thin_box", "blade", "crossed_plates", "letter_panel", "hourglass", "funnel", "paddle"}
    for shape in SHAPES.values():
        assert callable(shape.build)


# ----------------------------------------------------------------------------- plates


def test_sheet_is_a_rectangle_in_xz_with_normal_up():
    mesh = sheet((0.5, 0.3))
    assert len(mesh.faces) == 2 and len(mesh.vertices) == 4
    np.testing.assert_allclose(mesh.bounds, [[-0.25, 0, -0.15], [0.25, 0, 0.15]])
    np.testing.assert_allclose(mesh.face_normals, [[0, 1, 0]] * 2, atol=1e-12)
    assert len(mesh_boundary_edges(mesh)) == 4
    assert len(boundary_loops(mesh)) == 1


def test_sheet_resolution_tessellates():
    mesh = sheet((0.5, 0.3), resolution=(5, 3))
    assert len(mesh.faces) == 2 * 5 * 3 and len(mesh.vertices) == 6 * 4
    assert mesh.area == pytest.approx(0.15)
    assert len(mesh_boundary_edges(mesh)) == 2 * (5 + 3)
    np.testing.assert_allclose(mesh.face_normals[:, 1], 1.0)
    assert len(sheet((1, 1), resolution=4).faces) == 32


def test_sheet_rotation_and_center_are_applied():
    center, rot = np.array([0.3, 0.5, -0.2]), (20.0, -35.0, 50.0)
    flat, placed = sheet((0.5, 0.3), resolution=2), sheet((0.5, 0.3), center, rot, resolution=2)
    R = euler_matrix(rot)
    np.testing.assert_allclose(placed.vertices, flat.vertices @ R.T + center, atol=1e-12)
    np.testing.assert_allclose(placed.face_normals, np.tile(R @ [0, 1, 0], (len(placed.faces), 1)), atol=1e-12)
    # a sheet rotated 90 degrees about x stands up with its normal along +z
    upright = sheet((0.5, 0.3), rotation_deg=(90, 0, 0))
    np.testing.assert_allclose(upright.face_normals, [[0, 0, 1]] * 2, atol=1e-12)


def test_thin_box_size_and_volume():
    mesh = thin_box((0.5, 0.002, 0.3), center=(1.0, 2.0, 3.0))
    assert mesh.volume == pytest.approx(0.5 * 0.002 * 0.3)
    np.testing.assert_allclose(mesh.bounds, [[0.75, 1.999, 2.85], [1.25, 2.001, 3.15]])


def test_blade_zero_thickness_is_xy_sheet_and_thick_is_box():
    open_blade = blade(0.4, 0.2, 0.0, center=(0.1, 0.2, 0.3))
    np.testing.assert_allclose(open_blade.bounds, [[-0.1, 0.1, 0.3], [0.3, 0.3, 0.3]], atol=1e-12)
    np.testing.assert_allclose(open_blade.face_normals, [[0, 0, 1]] * 2, atol=1e-12)
    thick = blade(0.4, 0.2, 0.002)
    assert thick.volume == pytest.approx(0.4 * 0.2 * 0.002)
    np.testing.assert_allclose(thick.extents, [0.4, 0.2, 0.002])
    # the paddle is the same sheet, turning about its own middle
    np.testing.assert_allclose(paddle(0.4, 0.2, (0.1, 0.2, 0.3)).vertices, open_blade.vertices)


def test_crossed_plates_form_an_x_seen_from_above():
    length, height, t = 0.4, 0.3, 0.004
    thin = crossed_plates((length, height))
    assert len(boundary_loops(thin)) == 2  # two separate sheets
    # both plates are vertical (normals horizontal) and at +-45 degrees
    n = thin.face_normals
    np.testing.assert_allclose(n[:, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(n[:, 0]), np.sqrt(0.5), atol=1e-12)
    np.testing.assert_allclose(np.abs(n[:, 2]), np.sqrt(0.5), atol=1e-12)
    half = length / 2 * np.sqrt(0.5)
    np.testing.assert_allclose(thin.bounds, [[-half, -height / 2, -half], [half, height / 2, half]], atol=1e-12)
    thick = crossed_plates((length, height), t, center=(0.5, 0.5, 0.5))
    # two plates minus their t x t x height overlap at the crossing
    assert thick.volume == pytest.approx(2 * length * height * t - t * t * height, rel=1e-9)
    np.testing.assert_allclose(thick.centroid, [0.5, 0.5, 0.5], atol=1e-9)


# ----------------------------------------------------------------------------- letters


def test_letter_panel_LOB_has_three_glyph_holes():
    size = (0.6, 0.3)
    holes = letter_hole_polygons("LOB", size)
    # one hole per glyph; its interiors are the islands of material that stay:
    # "L" none, "O" its counter, "B" its two counters
    assert len(holes) == 3
    assert [len(h.interiors) for h in holes] == [0, 1, 2]

    mesh = letter_panel("LOB", size)
    # Boundary loops of the open sheet, counted as connected groups of boundary edges:
    #   1 outer rectangle
    # + 3 hole outlines (the outer contours of L, O and B)
    # + 3 island outlines (the counter of O and the two counters of B, whose material
    #   stays in place as separate pieces of the sheet)
    # = 7 loops.
    assert len(boundary_loops(mesh)) == 1 + 3 + 3

    # single-sided sheet facing +z, area = panel minus the glyph holes
    np.testing.assert_allclose(mesh.face_normals[:, 2], 1.0, atol=1e-9)
    np.testing.assert_allclose(mesh.vertices[:, 2], 0.0)
    hole_area = sum(h.area for h in holes)
    assert mesh.area == pytest.approx(size[0] * size[1] - hole_area, rel=1e-9)
    np.testing.assert_allclose(mesh.bounds[:, :2], [[-0.3, -0.15], [0.3, 0.15]], atol=1e-12)


def test_letter_panel_text_is_centred_and_fills_60_percent_of_height():
    w, h = 0.6, 0.3
    holes = letter_hole_polygons("LOB", (w, h))
    lo = np.min([p.bounds[:2] for p in holes], axis=0)
    hi = np.max([p.bounds[2:] for p in holes], axis=0)
    assert hi[1] - lo[1] == pytest.approx(0.6 * h, rel=1e-6)
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)
    # an explicit font size (em size in metres) is honoured: cap height ~0.73 em
    small = letter_hole_polygons("LOB", (w, h), font_size=0.05)
    height = max(p.bounds[3] for p in small) - min(p.bounds[1] for p in small)
    assert 0.03 < height < 0.05


def test_letter_panel_thick_is_extruded_and_placed():
    size, t = (0.6, 0.3), 0.004
    sheet_mesh = letter_panel("LOB", size)
    solid = letter_panel("LOB", size, t, center=(0.5, 0.4, 0.3), rotation_deg=(0, 90, 0))
    assert solid.volume == pytest.approx(sheet_mesh.area * t, rel=1e-9)
    # rotated 90 degrees about y, the panel's normal (+z) points along +x
    np.testing.assert_allclose(solid.extents, [t, 0.3, 0.6], atol=1e-9)
    np.testing.assert_allclose(solid.bounds.mean(axis=0), [0.5, 0.4, 0.3], atol=1e-9)


def test_letter_panel_with_kerning_and_shared_baselines_stays_conforming():
    # "AV" is kerned, and all letters share baseline and cap height: collinear
    # vertices across holes, the case where ear clipping alone leaves T-junctions
    text = "AVA MPM 8"
    holes = letter_hole_polygons(text, (1.2, 0.3))
    mesh = letter_panel(text, (1.2, 0.3))
    assert_clean(mesh)
    assert len(boundary_loops(mesh)) == 1 + len(holes) + sum(len(h.interiors) for h in holes)
    assert letter_panel(text, (1.2, 0.3), 0.003).is_watertight


# ----------------------------------------------------------------------------- revolution


def ring_radius(mesh, center, tol=1e-9):
    """Distances from the y axis through ``center`` of the vertices at height ``center[1]``."""
    center = np.asarray(center, dtype=float)
    sel = np.abs(mesh.vertices[:, 1] - center[1]) < tol
    assert sel.sum() >= 3
    d = mesh.vertices[sel] - center
    return np.hypot(d[:, 0], d[:, 2])


def test_hourglass_neck_bulbs_and_open_top():
    height, radius, neck = 0.5, 0.15, 0.02
    center = np.array([0.4, 0.6, 0.5])
    mesh = hourglass(height, radius, neck, center=center, segments=48)
    local = mesh.vertices - center
    r_mid = ring_radius(mesh, center)
    assert np.all(np.abs(r_mid - neck) <= 0.02 * neck)
    # the neck is the narrowest ring away from the ends; the bulbs reach `radius`
    r = np.hypot(local[:, 0], local[:, 2])
    assert r.max() == pytest.approx(radius, rel=0.01)
    upper = local[:, 1] > 0
    assert r[upper].max() == pytest.approx(radius, rel=0.01)
    assert r[~upper].max() == pytest.approx(radius, rel=0.01)
    np.testing.assert_allclose(mesh.bounds[:, 1], [center[1] - height / 2, center[1] + height / 2])
    # closed at the bottom (a pole on the axis), one open loop: the mouth at the top
    loops = boundary_loops(mesh)
    assert len(loops) == 1
    np.testing.assert_allclose(mesh.vertices[loops[0], 1], center[1] + height / 2)
    bottom = mesh.vertices[np.argmin(mesh.vertices[:, 1])]
    np.testing.assert_allclose(bottom[[0, 2]], center[[0, 2]], atol=1e-12)
    # normals point away from the axis at the bulbs' equator
    eq = np.abs(mesh.triangles_center[:, 1] - (center[1] - height / 4)) < 0.02 * height
    radial = mesh.triangles_center[eq] - center
    radial[:, 1] = 0
    assert np.all(np.einsum("ij,ij->i", mesh.face_normals[eq], radial) > 0)


def test_hourglass_glass_wall_is_closed_with_inner_neck_kept():
    height, radius, neck, wall = 0.5, 0.15, 0.02, 0.004
    glass = hourglass(height, radius, neck, wall_thickness=wall, segments=48)
    assert glass.is_watertight and glass.volume > 0
    r_mid = ring_radius(glass, (0.0, 0.0, 0.0))
    # the inner neck is neck_radius, the outer one a wall thickness further out
    assert np.abs(r_mid.min() - neck) <= 0.02 * neck
    assert r_mid.max() == pytest.approx(neck + wall, rel=0.02)
    # volume ~ inner surface area x wall thickness
    inner = hourglass(height, radius, neck, segments=48)
    assert glass.volume == pytest.approx(inner.area * wall, rel=0.1)
    with pytest.raises(ValueError):
        hourglass(height, radius, neck, wall_thickness=0.1)  # thicker than the neck's curvature radius


def test_hourglass_rotation_and_center_are_applied():
    center, rot = np.array([0.1, 0.2, 0.3]), (30.0, 0.0, 45.0)
    base = hourglass(0.5, 0.15, 0.02, segments=24)
    placed = hourglass(0.5, 0.15, 0.02, center=center, segments=24, rotation_deg=rot)
    np.testing.assert_allclose(placed.vertices, base.vertices @ euler_matrix(rot).T + center, atol=1e-12)


def test_funnel_radii_and_open_ends():
    top, pipe, cone_h, pipe_l = 0.2, 0.03, 0.15, 0.1
    center = np.array([0.5, 0.5, 0.5])
    mesh = funnel(top, pipe, cone_h, pipe_l, center=center, segments=40)
    local = mesh.vertices - center
    r = np.hypot(local[:, 0], local[:, 2])
    y0 = -(cone_h + pipe_l) / 2
    in_pipe = local[:, 1] <= y0 + pipe_l + 1e-12
    np.testing.assert_allclose(r[in_pipe], pipe, rtol=1e-12)
    np.testing.assert_allclose(r[np.isclose(local[:, 1], -y0)], top, rtol=1e-12)
    np.testing.assert_allclose(mesh.bounds[:, 1], center[1] + np.array([y0, -y0]))
    # cone radius grows linearly with height
    cone = ~in_pipe
    expected = pipe + (top - pipe) * (local[cone, 1] - (y0 + pipe_l)) / cone_h
    np.testing.assert_allclose(r[cone], expected, rtol=1e-9)
    # open at both ends: the top rim and the pipe outlet
    loops = boundary_loops(mesh)
    assert len(loops) == 2
    assert sorted(np.round([r[lp].mean() for lp in loops], 12)) == [pipe, top]
    placed = funnel(top, pipe, cone_h, pipe_l, center=center, segments=40, rotation_deg=(90, 0, 0))
    base = funnel(top, pipe, cone_h, pipe_l, segments=40)
    np.testing.assert_allclose(placed.vertices, base.vertices @ euler_matrix((90, 0, 0)).T + center, atol=1e-12)


def test_boundary_edges_of_closed_and_open_meshes():
    box = trimesh.creation.box()
    assert mesh_boundary_edges(box).shape == (0, 2) and not is_open(box)
    tri = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], process=False)
    edges = mesh_boundary_edges(tri)
    assert sorted(map(tuple, edges.tolist())) == [(0, 1), (0, 2), (1, 2)]
    assert is_open(tri)


@pytest.mark.parametrize(
    "call",
    [
        lambda: sheet((0.0, 1.0)),
        lambda: sheet((1.0, 1.0), resolution=0),
        lambda: thin_box((1.0, -0.1, 1.0)),
        lambda: blade(1.0, 1.0, -0.1),
        lambda: hourglass(1.0, 0.1, 0.2),
        lambda: funnel(0.2, 0.05, 0.0, 0.1),
        lambda: sheet((1.0, 1.0), center=(0, 0)),
    ],
)
def test_invalid_arguments_raise(call):
    with pytest.raises(ValueError):
        call()


# --------------------------------------------------------------------------- meshes the solver sees

import warp as wp  # noqa: E402


@wp.kernel
def _closest_points(mesh: wp.uint64, x: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    p = wp.tid()
    q = wp.mesh_query_point_no_sign(mesh, x[p], 0.05)
    out[p] = wp.mesh_eval_position(mesh, q.face, q.u, q.v)


def test_solver_colliders_give_exact_closest_points_next_to_a_letter_panel():
    """The paper panel's triangulation has slivers 0.6 m long and 4 mm wide. On them
    Warp's float32 closest point landed up to 0.6 mm beside the true one, so particles
    0.02 mm in front of the sheet read as farther than their step, skipped the
    crossing test and went through (5 of 216k particles in the first 2/30 s of
    `paper_panel` in finest mode, at 3 m/s). The solver's meshes have no edge longer
    than two coarse cells; the closest point of any point hovering over the panel's
    material must then be its projection, to within the crossing test's slack of
    0.01 fine cells."""
    from shapely import points as shp_points
    from shapely.prepared import prep

    from abmpm.compare.outcomes import _panel_material
    from abmpm.inputs import MAX_COLLIDER_EDGE_CELLS, rigid_bodies
    from abmpm.scene.loader import load_scene
    from abmpm.sim.collider_set import ColliderSet

    scene = load_scene("paper_panel")
    dx = scene.simulation.dx
    fine_dx = dx / scene.simulation.refinement.factor
    body = rigid_bodies(scene)[0]
    edges = np.linalg.norm(body.vertices[body.faces[:, [1, 2, 0]]] - body.vertices[body.faces], axis=2)
    assert edges.max() <= MAX_COLLIDER_EDGE_CELLS * dx * (1 + 1e-9)
    colliders = ColliderSet([body], "cpu")
    col = scene.colliders[0]
    rng = np.random.default_rng(3)
    local = rng.uniform([-0.4, -0.225], [0.4, 0.225], size=(20000, 2))
    solid = prep(_panel_material(col).buffer(-fine_dx))  # over material, a fine cell from any rim
    local = local[[solid.contains(p) for p in shp_points(local)]]
    height = rng.uniform(1e-5, 2e-4, len(local)) * rng.choice([-1.0, 1.0], len(local))  # both faces
    x = np.column_stack([local + np.asarray(col.center[:2]), np.full(len(local), col.center[2]) + height])
    out = wp.zeros(len(x), dtype=wp.vec3, device="cpu")
    wp.launch(_closest_points, len(x), inputs=[colliders.mesh.id, wp.array(x.astype(np.float32), dtype=wp.vec3), out],
              device="cpu")
    lateral = np.linalg.norm(out.numpy()[:, :2] - x[:, :2].astype(np.float32), axis=1)
    assert len(x) > 5000 and lateral.max() < 0.01 * fine_dx, lateral.max()


def test_collider_subdivision_stays_bounded_for_a_huge_sheet():
    """A 200 m floor under a 1 m domain at dx = 0.005 would need ~8e8 triangles of
    two cells: the limit grows instead, so the solver's copy stays within its budget."""
    from abmpm.geometry.meshes import limit_edge_length

    v = np.array([[-100.0, 0, -100.0], [100.0, 0, -100.0], [100.0, 0, 100.0], [-100.0, 0, 100.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    v2, f2 = limit_edge_length(v, f, 0.01, max_faces=200_000)
    assert 0 < len(f2) <= 200_000
    area = 0.5 * np.linalg.norm(np.cross(v2[f2[:, 1]] - v2[f2[:, 0]], v2[f2[:, 2]] - v2[f2[:, 0]]), axis=1).sum()
    assert abs(area - 200.0 * 200.0) < 1e-6 * 200.0 * 200.0  # the same surface
    # a small mesh is split to the limit asked for
    v3, f3 = limit_edge_length(v * 0.01, f, 0.1)
    assert np.linalg.norm(v3[f3[:, [1, 2, 0]]] - v3[f3], axis=2).max() <= 0.1 + 1e-12


# builder parameters a scene file does not set (they keep the builder's default)
NOT_IN_SCENE = {"blade": {"resolution"}, "letter_panel": {"font", "font_size"}, "hourglass": {"segments"},
                "funnel": {"segments"}, "paddle": {"thickness"}}
POSE = {"center", "rotation_deg"}  # the placement's, after the builder


def test_every_declared_parameter_is_a_builder_keyword():
    """The placement passes a builder exactly its shape's declared parameters, by
    name: each must be a keyword of the builder (else the build fails), and a builder
    parameter left out must be listed as not in scenes (a deliberate choice)."""
    import inspect

    for name, shape in SHAPES.items():
        params = set(inspect.signature(shape.build).parameters) - POSE
        declared = {p.name for p in shape.parameters}
        assert declared <= params, f"{name}: {sorted(declared - params)} are no keywords of its builder"
        assert params - declared == NOT_IN_SCENE.get(name, set()), name
