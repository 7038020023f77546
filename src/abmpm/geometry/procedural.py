"""Procedural collider shapes: sheet, thin box, blade, crossed plates, paddle,
letter panel, hourglass and funnel.

Every builder here returns a :class:`trimesh.Trimesh` in metres (y is up) with
float64 vertices, consistently wound faces and no degenerate triangles. The solver
treats colliders as thin surfaces, so open zero-thickness sheets are valid (and often
what a test wants: a blade of zero thickness is the hardest case for leakage); where a
``thickness`` is given the result is closed (watertight) with outward normals.

Placement follows the rest of the geometry package: a shape is built in its own frame
around the origin and placed with :func:`abmpm.geometry.meshes.place`,
``world = center + R @ local`` with ``R = euler_matrix(rotation_deg)`` (intrinsic XYZ
Euler angles in degrees).

The shapes a scene file can name are registered in
:mod:`abmpm.geometry.collider_shapes` (one module each, declaring the parameters a
scene sets); :func:`abmpm.geometry.placement.collider_mesh` passes a builder exactly
those, by name, and places the mesh from the collider's center and rotation.

The glyph outlines and triangulation of the letter panel are in
:mod:`abmpm.geometry.glyphs`, edge topology (boundary edges, loops) in
:mod:`abmpm.geometry.topology`.
"""

from __future__ import annotations

import math

import manifold3d
import numpy as np
import trimesh
from shapely.geometry import Polygon, box

from abmpm.geometry.arguments import non_negative, positive, vec3
from abmpm.geometry.glyphs import extrude, panel_polygons, triangulate_polygon
from abmpm.geometry.meshes import place

# ----------------------------------------------------------------------------- helpers


def _mesh(vertices, faces) -> trimesh.Trimesh:
    """A Trimesh with float64 vertices; duplicate vertices merged, nothing else changed
    (the builders below produce no degenerate faces, and dropping one would open a slit)."""
    mesh = trimesh.Trimesh(
        vertices=np.asarray(vertices, dtype=np.float64),
        faces=np.asarray(faces, dtype=np.int64),
        process=False,
    )
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    return mesh


def _grid(n_u: int, n_v: int) -> np.ndarray:
    """Faces of an (n_u+1) x (n_v+1) vertex grid (index ``i * (n_v + 1) + j``), two
    triangles per cell, wound so that the normal is ``d/du x d/dv``."""
    i, j = np.meshgrid(np.arange(n_u), np.arange(n_v), indexing="ij")
    a = (i * (n_v + 1) + j).ravel()
    b = a + (n_v + 1)  # i + 1
    c = b + 1  # i + 1, j + 1
    d = a + 1  # j + 1
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _resolution(resolution) -> tuple[int, int]:
    if resolution is None:
        return 1, 1
    r = np.broadcast_to(np.asarray(resolution), (2,))
    out = tuple(int(x) for x in r)
    if any(x < 1 for x in out) or not np.all(r == np.asarray(out)):
        raise ValueError(f"resolution must be a positive integer or a pair of them, got {resolution!r}")
    return out


def _rectangle(size_u: float, size_v: float, n_u: int, n_v: int, plane: str) -> trimesh.Trimesh:
    """Zero-thickness rectangle centred on the origin. ``plane="xz"``: u = z, v = x so
    the normal ``u x v`` is +y; ``plane="xy"``: u = x, v = y, normal +z."""
    u = np.linspace(-size_u / 2, size_u / 2, n_u + 1)
    v = np.linspace(-size_v / 2, size_v / 2, n_v + 1)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    zero = np.zeros_like(uu)
    if plane == "xz":
        pts = np.stack([vv, zero, uu], -1)
    else:
        pts = np.stack([uu, vv, zero], -1)
    return _mesh(pts.reshape(-1, 3), _grid(n_u, n_v))


# ----------------------------------------------------------------------------- plates


def sheet(size=(1.0, 1.0), center=(0.0, 0.0, 0.0), rotation_deg=(0.0, 0.0, 0.0), resolution=None):
    """Zero-thickness rectangle ``w x d`` in the xz-plane (normal +y before rotation).

    Open: its four sides are boundary edges. ``resolution`` (an int or ``(nx, nz)``)
    splits it into a grid of ``nx x nz`` cells of two triangles each; default one cell.
    """
    w, d = (positive(s, "sheet size") for s in np.broadcast_to(np.asarray(size, dtype=float), (2,)))
    nx, nz = _resolution(resolution)
    return place(_rectangle(d, w, nz, nx, "xz"), center, rotation_deg)


def thin_box(size=(1.0, 0.01, 1.0), center=(0.0, 0.0, 0.0), rotation_deg=(0.0, 0.0, 0.0)):
    """Closed box ``w x t x d`` (a plate when ``t`` is small), watertight, outward normals."""
    ext = vec3(size, "thin_box size")
    for s in ext:
        positive(s, "thin_box size")
    return place(_mesh(*_box_arrays(ext)), center, rotation_deg)


def _box_arrays(ext):
    box = trimesh.creation.box(extents=ext)
    return np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces)


def blade(length=1.0, height=1.0, thickness=0.0, center=(0.0, 0.0, 0.0), rotation_deg=(0.0, 0.0, 0.0), resolution=None):
    """A blade of ``length`` (x) by ``height`` (y) centred on ``center``.

    ``thickness == 0``: an open sheet in the xy-plane with normal +z (before rotation);
    ``thickness > 0``: a closed thin box of that thickness along z.
    """
    length = positive(length, "blade length")
    height = positive(height, "blade height")
    thickness = non_negative(thickness, "blade thickness")
    if thickness > 0.0:
        return thin_box((length, height, thickness), center, rotation_deg)
    nx, ny = _resolution(resolution)
    return place(_rectangle(length, height, nx, ny, "xy"), center, rotation_deg)


def crossed_plates(size=(1.0, 1.0), thickness=0.0, center=(0.0, 0.0, 0.0), rotation_deg=(0.0, 0.0, 0.0)):
    """Two vertical plates ``length x height`` crossing at their middle, at +45 and -45
    degrees about y, so that they form an X seen from above.

    ``thickness == 0``: two open sheets that intersect along the vertical axis (fine for
    a collider); ``thickness > 0``: the boolean union of two thin boxes (manifold3d),
    one closed watertight body.
    """
    length, height = (float(s) for s in np.broadcast_to(np.asarray(size, dtype=float), (2,)))
    length = positive(length, "crossed_plates length")
    height = positive(height, "crossed_plates height")
    thickness = non_negative(thickness, "crossed_plates thickness")
    parts = []
    for angle in (45.0, -45.0):
        if thickness > 0.0:
            part = thin_box((length, height, thickness), (0, 0, 0), (0.0, angle, 0.0))
        else:
            part = blade(length, height, 0.0, (0, 0, 0), (0.0, angle, 0.0))
        parts.append(part)
    if thickness > 0.0:
        merged = _union(parts)
    else:
        merged = _mesh(*_concat_arrays(parts))
    return place(merged, center, rotation_deg)


def _union(meshes) -> trimesh.Trimesh:
    """Boolean union of closed meshes with manifold3d in double precision.

    (``trimesh.boolean.union`` hands manifold3d float32 vertices, which moves the faces
    of a plate a tenth of a cell thick by ~1e-8 m; ``Mesh64`` keeps float64.)
    """
    solids = [
        manifold3d.Manifold(
            manifold3d.Mesh64(
                vert_properties=np.ascontiguousarray(m.vertices, dtype=np.float64),
                tri_verts=np.ascontiguousarray(m.faces, dtype=np.uint64),
            )
        )
        for m in meshes
    ]
    result = manifold3d.Manifold.batch_boolean(solids, manifold3d.OpType.Add).to_mesh64()
    merged = _mesh(np.asarray(result.vert_properties)[:, :3], np.asarray(result.tri_verts, dtype=np.int64))
    if not merged.is_watertight:  # pragma: no cover - manifold3d returns closed output
        raise RuntimeError("boolean union did not produce a closed mesh")
    return merged


def paddle(length=1.0, height=1.0, center=(0.0, 0.0, 0.0), rotation_deg=(0.0, 0.0, 0.0), thickness=0.0):
    """A flat paddle for rotating-paddle tests: a ``length`` (x) by ``height`` (y) sheet
    through ``center`` (so it turns about its own middle), normal +z before rotation.
    A positive ``thickness`` gives a closed thin box instead."""
    return blade(length, height, thickness, center, rotation_deg)


def _concat_arrays(meshes):
    verts, faces, offset = [], [], 0
    for m in meshes:
        verts.append(np.asarray(m.vertices, dtype=np.float64))
        faces.append(np.asarray(m.faces) + offset)
        offset += len(m.vertices)
    return np.concatenate(verts), np.concatenate(faces)


# ----------------------------------------------------------------------------- letters


def letter_panel(
    text="ABC",
    size=(1.0, 0.5),
    thickness=0.0,
    center=(0.0, 0.0, 0.0),
    rotation_deg=(0.0, 0.0, 0.0),
    font_size=None,
    font="DejaVu Sans",
):
    """A ``w x h`` panel in the xy-plane (normal +z) with holes shaped like the glyphs of
    ``text``.

    The hole is each glyph's filled shape, so the inner islands of letters such as "A",
    "O", "B" stay as (disconnected) pieces of material. ``font_size`` is the em size in
    metres; by default the text is scaled to fill ~60% of the panel height (and at most
    90% of its width) and centred. ``thickness == 0``: single-sided open sheet;
    ``thickness > 0``: closed extrusion, ``thickness`` along z, centred on the panel plane.
    """
    thickness = non_negative(thickness, "letter_panel thickness")
    polys = panel_polygons(text, size, font_size, font)
    parts = []
    for poly in polys:
        v2, f = triangulate_polygon(poly)
        if thickness > 0.0:
            parts.append(trimesh.Trimesh(*extrude(v2, f, thickness), process=False))
        else:
            parts.append(trimesh.Trimesh(np.column_stack([v2, np.zeros(len(v2))]), f, process=False))
    mesh = _mesh(*_concat_arrays(parts))
    return place(mesh, center, rotation_deg)


HOLE_SEGMENTS = 32  # a round hole is a regular polygon of this many sides


def perforated_plate(size=(1.0, 1.0), hole_diameter=0.1, holes=1, center=(0.0, 0.0, 0.0),
                     rotation_deg=(0.0, 0.0, 0.0)):
    """A zero-thickness ``w x d`` plate in the xz-plane (normal +y before rotation) with
    ``holes`` round holes of ``hole_diameter`` evenly spaced along x on its centre line
    (each a regular HOLE_SEGMENTS-gon inscribed in the circle)."""
    w, d = (positive(s, "perforated_plate size") for s in np.broadcast_to(np.asarray(size, dtype=float), (2,)))
    dia = positive(hole_diameter, "perforated_plate hole_diameter")
    n = int(holes)
    if n < 1 or dia >= min(w / n, d):
        raise ValueError(f"perforated_plate: {n} holes of diameter {dia} do not fit in a {w} x {d} plate")
    pitch = w / n
    t = 2 * np.pi * np.arange(HOLE_SEGMENTS) / HOLE_SEGMENTS
    rings = [np.column_stack([-w / 2 + pitch * (k + 0.5) + dia / 2 * np.cos(t), dia / 2 * np.sin(t)])
             for k in range(n)]
    v2, f = triangulate_polygon(Polygon(box(-w / 2, -d / 2, w / 2, d / 2).exterior.coords,
                                        [r[::-1] for r in rings]))
    # plane coordinates (x, z) -> (x, 0, -z): counter-clockwise in the xz-view keeps +y
    mesh = _mesh(np.column_stack([v2[:, 0], np.zeros(len(v2)), -v2[:, 1]]), f)
    return place(mesh, center, rotation_deg)


# ----------------------------------------------------------------------------- revolution


def _revolve(profile: np.ndarray, segments: int) -> trimesh.Trimesh:
    """Surface of revolution about +y of the polyline ``profile`` ((N, 2) of ``(r, y)``).

    Points with ``r == 0`` become a single pole vertex (triangle fan), so a profile that
    starts and ends on the axis gives a closed surface. Faces are wound so that the
    normal points to the right of the direction of travel in the (r, y) half-plane,
    i.e. away from the axis for a profile that goes upwards.
    """
    segments = int(segments)
    if segments < 3:
        raise ValueError(f"segments must be at least 3, got {segments}")
    profile = np.asarray(profile, dtype=np.float64)
    theta = 2 * np.pi * np.arange(segments) / segments
    cos, sin = np.cos(theta), np.sin(theta)
    verts, rings = [], []
    n = 0
    for r, y in profile:
        if r <= 0.0:
            verts.append([[0.0, y, 0.0]])
            rings.append(np.full(segments, n))
            n += 1
        else:
            verts.append(np.stack([r * cos, np.full(segments, y), -r * sin], 1))
            rings.append(n + np.arange(segments))
            n += segments
    faces = []
    nxt = np.roll(np.arange(segments), -1)
    for k in range(len(profile) - 1):
        a, b = rings[k], rings[k + 1]
        # quad (a_i, a_i+1, b_i+1, b_i); a pole row collapses one triangle of each pair
        t1 = np.stack([a, a[nxt], b[nxt]], 1)
        t2 = np.stack([a, b[nxt], b], 1)
        if a[0] != a[1]:
            faces.append(t1)
        if b[0] != b[1]:
            faces.append(t2)
        if a[0] == a[1] and b[0] == b[1]:
            raise ValueError("profile has two consecutive points on the axis")
    return _mesh(np.concatenate(verts), np.concatenate(faces))


def _hourglass_profile(height: float, radius: float, neck_radius: float, samples: int):
    """Inner profile ``(r, y)`` of the hourglass, from the bottom pole (0, 0) up to the
    open mouth at y = height; the neck (r = neck_radius) is at y = height / 2 exactly."""
    half = height / 2
    n_exp = 2.5  # superellipse exponent of a bulb (2 = ellipse, larger = boxier)
    mouth = 0.55  # mouth radius as a fraction of the bulb radius
    c_top = 1.0 - mouth**n_exp

    def r_of(u, upper):
        # u = distance from the neck in units of half the height (0 neck, 1 end)
        u = np.asarray(u, dtype=np.float64)
        # neck side of a bulb: a smooth waist, r = neck + (R - neck) sin^2(pi u),
        # curvature radius half^2 / (2 pi^2 (R - neck)) at the neck
        waist = neck_radius + (radius - neck_radius) * np.sin(np.pi * np.minimum(u, 0.5)) ** 2
        # far side: a superellipse quarter that closes on the axis (bottom) or stops at
        # the mouth (top); both have zero slope at the equator u = 0.5, like the waist
        s = np.clip(2.0 * u - 1.0, 0.0, 1.0)
        c = c_top if upper else 1.0
        cap = radius * np.clip(1.0 - c * s**n_exp, 0.0, None) ** (1.0 / n_exp)
        return np.where(u <= 0.5, waist, cap)

    # dense parameter grid -> arc-length resampling, with the neck point kept exactly
    dense = 4000
    parts = []
    for upper in (False, True):
        u = np.linspace(0.0, 1.0, dense)
        r = r_of(u, upper)
        y = half + (u * half if upper else -u * half)
        parts.append((r, y))
    r = np.concatenate([parts[0][0][::-1], parts[1][0][1:]])
    y = np.concatenate([parts[0][1][::-1], parts[1][1][1:]])
    r[0] = 0.0  # bottom pole
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(r), np.diff(y)))])
    i_neck = dense - 1
    n_low = max(8, int(round(samples * s[i_neck] / s[-1])))
    n_up = max(8, samples - n_low)
    s_new = np.concatenate(
        [np.linspace(0.0, s[i_neck], n_low + 1), np.linspace(s[i_neck], s[-1], n_up + 1)[1:]]
    )
    prof = np.stack([np.interp(s_new, s, r), np.interp(s_new, s, y)], 1)
    prof[n_low] = (neck_radius, half)
    prof[0] = (0.0, 0.0)
    prof[-1, 1] = height
    return prof


def _offset_profile(profile: np.ndarray, distance: float) -> np.ndarray:
    """Offset an ``(r, y)`` polyline by ``distance`` to the right of travel (outwards)."""
    p = profile
    tangent = np.gradient(p, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], 1)
    out = p + distance * normal
    seg_in, seg_out = np.diff(p, axis=0), np.diff(out, axis=0)
    if np.any(np.einsum("ij,ij->i", seg_in, seg_out) <= 0):
        raise ValueError("wall_thickness is too large for the curvature of the hourglass profile")
    return out


def hourglass(
    height=1.0,
    radius=0.3,
    neck_radius=0.05,
    center=(0.0, 0.0, 0.0),
    wall_thickness=0.0,
    segments=64,
    rotation_deg=(0.0, 0.0, 0.0),
):
    """A glass hourglass: surface of revolution about y of a smooth two-bulb profile.

    The bulbs have radius ``radius``; the neck of radius ``neck_radius`` sits at
    mid-height, which is placed at ``center``. The bottom is closed (the profile meets
    the axis, so liquid collects) and the top is open (a mouth of ~0.55 ``radius``).
    ``wall_thickness == 0``: one open surface (inner glass face, normals away from the
    axis). ``wall_thickness > 0``: hollow glass whose inner face is the profile above and
    whose outer face is offset outwards by ``wall_thickness`` (so the glass reaches a
    wall thickness below ``center[1] - height / 2``), joined by a flat lip at the rim
    height; closed and watertight. The offset must stay below the radius of curvature
    of the neck, ``(height / 2)**2 / (2 pi^2 (radius - neck_radius))``, else ValueError.
    """
    height = positive(height, "hourglass height")
    radius = positive(radius, "hourglass radius")
    neck_radius = positive(neck_radius, "hourglass neck_radius")
    if neck_radius >= radius:
        raise ValueError("hourglass neck_radius must be smaller than radius")
    wall = non_negative(wall_thickness, "hourglass wall_thickness")
    segments = int(segments)
    prof = _hourglass_profile(height, radius, neck_radius, max(48, 2 * segments))
    if wall > 0.0:
        outer = _offset_profile(prof, wall)
        outer[0, 0] = 0.0  # outer bottom pole, a wall thickness below the inner one
        neck = int(np.argmin(np.abs(prof[:, 1] - height / 2)))
        outer[neck] = (neck_radius + wall, height / 2)  # the neck is vertical: exact offset
        # the mouth leans inwards, so the offset face rises above the rim: cut it at the
        # rim height, where a flat lip (an annulus) joins it to the inner face
        k = int(np.argmax(outer[:, 1] >= height)) if np.any(outer[:, 1] >= height) else len(outer) - 1
        a, b = outer[k - 1], outer[k]
        lip = a + (b - a) * (height - a[1]) / (b[1] - a[1]) if b[1] != a[1] else b.copy()
        lip[1] = height
        keep = outer[:k]
        if np.hypot(*(keep[-1] - lip)) <= 1e-9 * height:
            keep = keep[:-1]
        outer = np.concatenate([keep, lip[None]])
        # outer face upwards from its pole (normals away from the axis), the lip inwards
        # (normal up), the inner face downwards to its pole (normals towards the axis,
        # i.e. out of the glass): the revolved loop encloses the glass wall
        loop = np.concatenate([outer, prof[::-1]])
        mesh = _revolve(loop, segments)
        if mesh.volume < 0:  # pragma: no cover - orientation fixed by construction
            mesh.invert()
    else:
        mesh = _revolve(prof, segments)
    mesh.vertices[:, 1] -= height / 2
    return place(mesh, center, rotation_deg)


def funnel(
    top_radius=0.3,
    pipe_radius=0.05,
    cone_height=0.3,
    pipe_length=0.2,
    center=(0.0, 0.0, 0.0),
    segments=64,
    rotation_deg=(0.0, 0.0, 0.0),
):
    """An open cone narrowing downwards into a straight pipe, zero thickness, open at
    both ends (normals away from the axis).

    The axis is y; the pipe spans ``[0, pipe_length]`` and the cone
    ``[pipe_length, pipe_length + cone_height]`` in the funnel's own frame, and the
    whole is shifted so that ``center`` is the middle of its height on the axis.
    """
    top_radius = positive(top_radius, "funnel top_radius")
    pipe_radius = positive(pipe_radius, "funnel pipe_radius")
    cone_height = positive(cone_height, "funnel cone_height")
    pipe_length = non_negative(pipe_length, "funnel pipe_length")
    segments = int(segments)
    spacing = 2 * np.pi * max(top_radius, pipe_radius) / max(segments, 3)
    slant = math.hypot(top_radius - pipe_radius, cone_height)
    n_cone = int(np.clip(math.ceil(slant / spacing), 1, 256))
    rows = [(pipe_radius, pipe_length + cone_height * k / n_cone) for k in range(n_cone + 1)]
    rows = [(pipe_radius + (top_radius - pipe_radius) * k / n_cone, y) for k, (_, y) in enumerate(rows)]
    if pipe_length > 0.0:
        n_pipe = int(np.clip(math.ceil(pipe_length / spacing), 1, 256))
        pipe = [(pipe_radius, pipe_length * k / n_pipe) for k in range(n_pipe)]
        rows = pipe + rows
    mesh = _revolve(np.array(rows), segments)
    mesh.vertices[:, 1] -= (pipe_length + cone_height) / 2
    return place(mesh, center, rotation_deg)


__all__ = [
    "blade",
    "crossed_plates",
    "funnel",
    "hourglass",
    "letter_panel",
    "paddle",
    "perforated_plate",
    "sheet",
    "thin_box",
]
