"""Procedural boundary geometry for rigid colliders.

Every function here returns a :class:`trimesh.Trimesh` in metres (y is up) with
float64 vertices, consistently wound faces and no degenerate triangles. The solver
treats colliders as thin surfaces, so open zero-thickness sheets are valid (and often
what a test wants: a blade of zero thickness is the hardest case for leakage); where a
``thickness`` is given the result is closed (watertight) with outward normals.

Placement follows the rest of the geometry package: a shape is built in its own frame
around the origin and placed as ``world = center + R @ local`` with
``R = euler_matrix(rotation_deg)`` (intrinsic XYZ Euler angles in degrees).

``PROCEDURAL`` maps the names used in scene files to the builder functions.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh

from abmpm.geometry.meshes import transform_mesh

# ----------------------------------------------------------------------------- helpers


def _vec3(value, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be three finite numbers, got {value!r}")
    return v


def _positive(value, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return v


def _non_negative(value, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"{name} must be a non-negative number, got {value!r}")
    return v


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


def _place(mesh: trimesh.Trimesh, center, rotation_deg) -> trimesh.Trimesh:
    out = transform_mesh(mesh, 1.0, _vec3(rotation_deg, "rotation_deg"), _vec3(center, "center"))
    out.vertices = np.ascontiguousarray(out.vertices, dtype=np.float64)
    return out


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


# ----------------------------------------------------------------------------- topology


def mesh_boundary_edges(mesh: trimesh.Trimesh) -> np.ndarray:
    """Edges used by exactly one face, ``(K, 2)`` int64 vertex indices (sorted pairs)."""
    edges = np.asarray(mesh.edges_sorted, dtype=np.int64)
    if len(edges) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    idx = trimesh.grouping.group_rows(edges, require_count=1)
    return edges[np.asarray(idx, dtype=np.int64).reshape(-1)]


def is_open(mesh: trimesh.Trimesh) -> bool:
    """True when the surface has a boundary (some edge belongs to only one face)."""
    return len(mesh_boundary_edges(mesh)) > 0


def boundary_loops(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    """The boundary edges grouped into connected components (one per hole outline),
    each as the array of its vertex indices. Loops that touch at a vertex count as one."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = mesh_boundary_edges(mesh)
    if len(edges) == 0:
        return []
    verts, inv = np.unique(edges.ravel(), return_inverse=True)
    e = inv.reshape(-1, 2)
    n = len(verts)
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    return [verts[labels == k] for k in range(count)]


# ----------------------------------------------------------------------------- plates


def sheet(size=(1.0, 1.0), center=(0.0, 0.0, 0.0), rotation_deg=(0.0, 0.0, 0.0), resolution=None):
    """Zero-thickness rectangle ``w x d`` in the xz-plane (normal +y before rotation).

    Open: its four sides are boundary edges. ``resolution`` (an int or ``(nx, nz)``)
    splits it into a grid of ``nx x nz`` cells of two triangles each; default one cell.
    """
    w, d = (_positive(s, "sheet size") for s in np.broadcast_to(np.asarray(size, dtype=float), (2,)))
    nx, nz = _resolution(resolution)
    return _place(_rectangle(d, w, nz, nx, "xz"), center, rotation_deg)


def thin_box(size=(1.0, 0.01, 1.0), center=(0.0, 0.0, 0.0), rotation_deg=(0.0, 0.0, 0.0)):
    """Closed box ``w x t x d`` (a plate when ``t`` is small), watertight, outward normals."""
    ext = _vec3(size, "thin_box size")
    for s in ext:
        _positive(s, "thin_box size")
    return _place(_mesh(*_box_arrays(ext)), center, rotation_deg)


def _box_arrays(ext):
    box = trimesh.creation.box(extents=ext)
    return np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces)


def blade(length=1.0, height=1.0, thickness=0.0, center=(0.0, 0.0, 0.0), rotation_deg=(0.0, 0.0, 0.0), resolution=None):
    """A blade of ``length`` (x) by ``height`` (y) centred on ``center``.

    ``thickness == 0``: an open sheet in the xy-plane with normal +z (before rotation);
    ``thickness > 0``: a closed thin box of that thickness along z.
    """
    length = _positive(length, "blade length")
    height = _positive(height, "blade height")
    thickness = _non_negative(thickness, "blade thickness")
    if thickness > 0.0:
        return thin_box((length, height, thickness), center, rotation_deg)
    nx, ny = _resolution(resolution)
    return _place(_rectangle(length, height, nx, ny, "xy"), center, rotation_deg)


def crossed_plates(size=(1.0, 1.0), thickness=0.0, center=(0.0, 0.0, 0.0), rotation_deg=(0.0, 0.0, 0.0)):
    """Two vertical plates ``length x height`` crossing at their middle, at +45 and -45
    degrees about y, so that they form an X seen from above.

    ``thickness == 0``: two open sheets that intersect along the vertical axis (fine for
    a collider); ``thickness > 0``: the boolean union of two thin boxes (manifold3d),
    one closed watertight body.
    """
    length, height = (float(s) for s in np.broadcast_to(np.asarray(size, dtype=float), (2,)))
    length = _positive(length, "crossed_plates length")
    height = _positive(height, "crossed_plates height")
    thickness = _non_negative(thickness, "crossed_plates thickness")
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
    return _place(merged, center, rotation_deg)


def _union(meshes) -> trimesh.Trimesh:
    """Boolean union of closed meshes with manifold3d in double precision.

    (``trimesh.boolean.union`` hands manifold3d float32 vertices, which moves the faces
    of a plate a tenth of a cell thick by ~1e-8 m; ``Mesh64`` keeps float64.)
    """
    import manifold3d

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

_TEXT_EM = 100.0  # glyphs are built at this size and scaled down (finer curve flattening)
_CURVE_STEPS = 8  # line pieces per Bezier segment of a glyph outline


def _glyph_rings(text: str, font: str):
    """Closed outline rings of ``text`` (font units at size ``_TEXT_EM``) as (N, 2) arrays."""
    from matplotlib.font_manager import FontProperties
    from matplotlib.path import Path
    from matplotlib.textpath import TextPath

    try:
        path = TextPath((0.0, 0.0), text, size=_TEXT_EM, prop=FontProperties(family=font))
    except (AttributeError, ValueError, IndexError):
        # matplotlib fails on text whose characters have no outline at all (e.g. a
        # zero-width space): there is nothing to cut out
        return []
    rings, current = [], []
    t = np.linspace(0.0, 1.0, _CURVE_STEPS + 1)[1:]
    for segment, code in path.iter_bezier():
        if code == Path.MOVETO:
            if len(current) >= 3:
                rings.append(np.array(current))
            current = [segment.control_points[0]]
        elif code == Path.LINETO:
            current.append(segment.control_points[-1])
        elif code in (Path.CURVE3, Path.CURVE4):
            current.extend(segment(t))
        elif code == Path.CLOSEPOLY:
            if len(current) >= 3:
                rings.append(np.array(current))
            current = []
    if len(current) >= 3:
        rings.append(np.array(current))
    return rings


def _glyph_polygons(text: str, font: str):
    """The filled glyph shapes of ``text`` as a shapely geometry in font units.

    Outline rings are nested by containment: a ring at even depth is an outer contour
    (filled), at odd depth a counter (the inside of "O"). Each filled region is its
    outer ring minus its direct children; the union merges touching letters.
    """
    from shapely.geometry import Polygon
    from shapely.ops import unary_union

    polys = []
    for ring in _glyph_rings(text, font):
        p = Polygon(ring).buffer(0)
        if p.is_empty or p.area <= 1e-9 * _TEXT_EM**2:
            continue
        if p.geom_type == "MultiPolygon":
            p = max(p.geoms, key=lambda g: g.area)
        polys.append(Polygon(p.exterior))
    order = sorted(range(len(polys)), key=lambda k: -polys[k].area)
    polys = [polys[k] for k in order]
    parent = [-1] * len(polys)
    for k, p in enumerate(polys):
        probe = p.representative_point()
        for j in range(k - 1, -1, -1):  # smallest larger ring containing this one
            if polys[j].area > p.area and polys[j].contains(probe) and polys[j].contains(p.buffer(-1e-6 * _TEXT_EM)):
                parent[k] = j
                break
    depth = []
    for k in range(len(polys)):
        d, j = 0, parent[k]
        while j >= 0:
            d, j = d + 1, parent[j]
        depth.append(d)
    filled = []
    for k, p in enumerate(polys):
        if depth[k] % 2:
            continue
        children = [polys[j] for j in range(len(polys)) if parent[j] == k]
        filled.append(p.difference(unary_union(children)) if children else p)
    return unary_union(filled)


def _as_polygons(geom):
    if geom.is_empty:
        return []
    if geom.geom_type == "Polygon":
        return [geom]
    if geom.geom_type in ("MultiPolygon", "GeometryCollection"):
        return [g for sub in geom.geoms for g in _as_polygons(sub)]
    return []


def _clean_polygon(poly, tol: float):
    """Drop collinear and near-duplicate vertices (they would give zero-area triangles)."""
    from shapely.geometry import Polygon
    from shapely.geometry.polygon import orient

    out = poly.simplify(tol, preserve_topology=True)
    if out.is_empty or out.geom_type != "Polygon":
        return None
    out = orient(Polygon(out.exterior, [r for r in out.interiors if Polygon(r).area > tol * tol]), 1.0)
    return out if out.is_valid and out.area > 0 else None


def _text_layout(text, size, font_size, font):
    """Glyph geometry scaled to metres and centred on the origin of the panel."""
    from shapely import affinity

    w, h = size
    glyphs = _glyph_polygons(text, font)
    if glyphs.is_empty:
        raise ValueError(f"letter_panel: text {text!r} has no visible glyphs")
    x0, y0, x1, y1 = glyphs.bounds
    if font_size is None:
        # fill ~60% of the panel height with the glyphs, but keep them inside 90% of the width
        scale = min(0.6 * h / (y1 - y0), 0.9 * w / (x1 - x0))
    else:
        scale = _positive(font_size, "font_size") / _TEXT_EM
    glyphs = affinity.translate(glyphs, -(x0 + x1) / 2, -(y0 + y1) / 2)
    return affinity.scale(glyphs, scale, scale, origin=(0.0, 0.0))


def letter_hole_polygons(text="ABC", size=(1.0, 0.5), font_size=None, font="DejaVu Sans"):
    """The holes cut into a :func:`letter_panel`: one shapely polygon per glyph region
    (panel frame, metres, panel centred on the origin, clipped to the panel).

    A hole is the glyph's filled shape, so the counters of "A", "O", "B" appear as the
    polygon's ``interiors`` (the island of material that stays inside the hole).
    """
    from shapely.geometry import box

    w, h = (_positive(s, "letter_panel size") for s in np.broadcast_to(np.asarray(size, dtype=float), (2,)))
    glyphs = _text_layout(str(text), (w, h), font_size, font)
    glyphs = glyphs.intersection(box(-w / 2, -h / 2, w / 2, h / 2))
    return sorted(_as_polygons(glyphs), key=lambda p: p.bounds[0])


def _panel_polygons(text, size, font_size, font):
    from shapely.geometry import box
    from shapely.ops import unary_union

    w, h = (_positive(s, "letter_panel size") for s in np.broadcast_to(np.asarray(size, dtype=float), (2,)))
    holes = letter_hole_polygons(text, (w, h), font_size, font)
    panel = box(-w / 2, -h / 2, w / 2, h / 2)
    if holes:
        panel = panel.difference(unary_union(holes))
    tol = 1e-7 * max(w, h)
    polys = [_clean_polygon(p, tol) for p in _as_polygons(panel)]
    return [p for p in polys if p is not None]


def _cross2(v, faces):
    a, b, c = (v[faces[:, k]] for k in range(3))
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


def _repair_slivers(v, faces, rel=1e-9):
    """Remove zero-area triangles from a 2D triangulation without opening it.

    Ear clipping emits a zero-area triangle ``(a, b, c)`` when vertices of different
    rings are collinear (letters share the baseline and cap height). Such a triangle
    cannot simply be dropped (its long edge ``a-c`` is shared with a neighbour
    ``(a, c, d)``), so the pair is re-split through the middle vertex ``b`` into
    ``(a, b, d)`` and ``(b, c, d)``: same area, same boundary, no sliver.
    """
    faces = faces.copy()
    scale = float(np.ptp(v, axis=0).max()) if len(v) else 1.0
    for _ in range(4 * len(faces) + 10):
        tri = v[faces]
        edge_len = np.linalg.norm(tri - np.roll(tri, -1, axis=1), axis=2)  # edge k: k -> k+1
        longest = edge_len.max(axis=1)
        height = np.abs(_cross2(v, faces)) / np.maximum(longest, 1e-300)
        bad = np.nonzero(height <= rel * scale)[0]
        if len(bad) == 0:
            return faces
        f = bad[0]
        k = int(np.argmax(edge_len[f]))
        a, c, b = faces[f, k], faces[f, (k + 1) % 3], faces[f, (k + 2) % 3]
        shares = (faces == a).any(axis=1) & (faces == c).any(axis=1)
        shares[f] = False
        nbr = np.nonzero(shares)[0]
        if len(nbr) != 1:
            if len(nbr) == 0 and edge_len[f].min() <= rel * scale:
                faces = np.delete(faces, f, axis=0)  # a duplicated point on the boundary
                continue
            raise RuntimeError("cannot repair a degenerate triangle of the letter panel")
        g = nbr[0]
        d = faces[g][(faces[g] != a) & (faces[g] != c)][0]
        faces[f] = (a, b, d)
        faces[g] = (b, c, d)
    raise RuntimeError("letter panel triangulation did not converge")


def _split_t_junctions(v, faces, rel=1e-9):
    """Make a 2D triangulation conforming: split every triangle whose edge has another
    vertex lying on it.

    Ear clipping is not exact on collinear input: when letters share the baseline or
    the cap height it may emit one long triangle edge along that line while the
    vertices in between belong to other triangles (a "T-junction"). The area is still
    covered, but the long edge then counts as a boundary edge and the hole outlines
    of the sheet are no longer closed loops. Splitting the long edge at the hanging
    vertex restores a watertight edge structure.
    """
    scale = float(np.ptp(v, axis=0).max()) if len(v) else 1.0
    tol = rel * scale
    faces = faces.copy()
    for _ in range(len(v) + 10):
        directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        once = np.asarray(trimesh.grouping.group_rows(np.sort(directed, axis=1), require_count=1), dtype=np.int64)
        once = once.reshape(-1)
        split = {}
        for chunk in range(0, len(once), 256):
            idx = once[chunk : chunk + 256]
            a, b = v[directed[idx, 0]], v[directed[idx, 1]]
            ab = b - a
            length2 = np.einsum("ij,ij->i", ab, ab)
            rel_pos = v[None, :, :] - a[:, None, :]
            t = np.einsum("kij,kj->ki", rel_pos, ab) / length2[:, None]
            dist = np.abs(rel_pos[:, :, 0] * ab[:, None, 1] - rel_pos[:, :, 1] * ab[:, None, 0]) / np.sqrt(length2)[:, None]
            length = np.sqrt(length2)[:, None]
            hit = (dist <= tol) & (t * length > tol) & ((1.0 - t) * length > tol)
            for row in np.nonzero(hit.any(axis=1))[0]:
                e = idx[row]
                f = e % len(faces)
                if f in split:
                    continue
                cand = np.nonzero(hit[row])[0]
                split[f] = (e // len(faces), cand[np.argmin(t[row, cand])])
        if not split:
            return faces
        new = []
        for f, (k, m) in split.items():
            a, b, c = faces[f, k], faces[f, (k + 1) % 3], faces[f, (k + 2) % 3]
            faces[f] = (a, m, c)
            new.append((m, b, c))
        faces = np.concatenate([faces, np.asarray(new, dtype=faces.dtype)])
    raise RuntimeError("letter panel triangulation: T-junction repair did not converge")


def _triangulate(poly):
    """Earcut triangulation of a shapely polygon: ``(V, 2)`` float64, ``(F, 3)``
    counter-clockwise (normal +z), conforming (no T-junctions), no zero-area triangles."""
    vertices, faces = trimesh.creation.triangulate_polygon(poly, engine="earcut")
    flat = trimesh.Trimesh(np.column_stack([vertices, np.zeros(len(vertices))]), faces, process=False)
    flat.merge_vertices()  # the closing point of each ring comes back as a second vertex
    flat.remove_unreferenced_vertices()
    vertices = np.asarray(flat.vertices[:, :2], dtype=np.float64)
    faces = _split_t_junctions(vertices, np.asarray(flat.faces, dtype=np.int64))
    faces = _repair_slivers(vertices, faces)
    flip = _cross2(vertices, faces) < 0
    faces[flip] = faces[flip][:, ::-1]
    return vertices, faces


def _extrude(v2, faces, thickness):
    """Closed prism of a CCW 2D triangulation, z in [-t/2, t/2], outward normals."""
    n = len(v2)
    h = thickness / 2
    verts = np.concatenate([np.column_stack([v2, np.full(n, -h)]), np.column_stack([v2, np.full(n, h)])])
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    once = trimesh.grouping.group_rows(np.sort(directed, axis=1), require_count=1)
    i, j = directed[np.asarray(once, dtype=np.int64).reshape(-1)].T  # material on the left of i -> j
    sides = np.concatenate([np.stack([i, j, j + n], 1), np.stack([i, j + n, i + n], 1)])
    return verts, np.concatenate([faces[:, ::-1], faces + n, sides])


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
    thickness = _non_negative(thickness, "letter_panel thickness")
    polys = _panel_polygons(text, size, font_size, font)
    parts = []
    for poly in polys:
        v2, f = _triangulate(poly)
        if thickness > 0.0:
            parts.append(trimesh.Trimesh(*_extrude(v2, f, thickness), process=False))
        else:
            parts.append(trimesh.Trimesh(np.column_stack([v2, np.zeros(len(v2))]), f, process=False))
    mesh = _mesh(*_concat_arrays(parts))
    return _place(mesh, center, rotation_deg)


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
    height = _positive(height, "hourglass height")
    radius = _positive(radius, "hourglass radius")
    neck_radius = _positive(neck_radius, "hourglass neck_radius")
    if neck_radius >= radius:
        raise ValueError("hourglass neck_radius must be smaller than radius")
    wall = _non_negative(wall_thickness, "hourglass wall_thickness")
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
    return _place(mesh, center, rotation_deg)


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
    top_radius = _positive(top_radius, "funnel top_radius")
    pipe_radius = _positive(pipe_radius, "funnel pipe_radius")
    cone_height = _positive(cone_height, "funnel cone_height")
    pipe_length = _non_negative(pipe_length, "funnel pipe_length")
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
    return _place(mesh, center, rotation_deg)


PROCEDURAL = {
    "sheet": sheet,
    "thin_box": thin_box,
    "blade": blade,
    "crossed_plates": crossed_plates,
    "letter_panel": letter_panel,
    "hourglass": hourglass,
    "funnel": funnel,
    "paddle": paddle,
}

__all__ = [
    "PROCEDURAL",
    "blade",
    "boundary_loops",
    "crossed_plates",
    "funnel",
    "hourglass",
    "is_open",
    "letter_hole_polygons",
    "letter_panel",
    "mesh_boundary_edges",
    "paddle",
    "sheet",
    "thin_box",
]
