"""Text for the letter panel: glyph outlines as polygons, and conforming triangulations.

The glyphs of a string are read from a font with matplotlib (outline rings at a
large em size, Bezier curves flattened), nested by containment into filled shapes
with shapely, scaled into the panel and cut out of it (:func:`panel_polygons`). Each
resulting polygon is triangulated by ear clipping and repaired into a conforming
triangulation without zero-area triangles (:func:`triangulate_polygon`), and can be
extruded into a closed prism (:func:`extrude`). The panel itself (placement, merged
mesh) is built by :func:`abmpm.geometry.procedural.letter_panel`.
"""

from __future__ import annotations

import unicodedata

import numpy as np
import trimesh
from matplotlib.font_manager import FontProperties, findfont
from matplotlib.ft2font import FT2Font
from matplotlib.path import Path
from matplotlib.textpath import TextPath
from scipy.spatial import cKDTree
from shapely import affinity
from shapely.geometry import Polygon, box
from shapely.geometry.polygon import orient
from shapely.ops import unary_union

from abmpm.geometry.arguments import positive
from abmpm.geometry.topology import boundary_halfedges, halfedges

__all__ = ["extrude", "letter_hole_polygons", "panel_polygons", "triangulate_polygon"]

_TEXT_EM = 100.0  # glyphs are built at this size and scaled down (finer curve flattening)
_CURVE_STEPS = 8  # line pieces per Bezier segment of a glyph outline


def _glyph_rings(text: str, font: str):
    """Closed outline rings of ``text`` (font units at size ``_TEXT_EM``) as (N, 2) arrays."""
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
    out = poly.simplify(tol, preserve_topology=True)
    if out.is_empty or out.geom_type != "Polygon":
        return None
    out = orient(Polygon(out.exterior, [r for r in out.interiors if Polygon(r).area > tol * tol]), 1.0)
    return out if out.is_valid and out.area > 0 else None


def _check_characters(text: str, font: str) -> None:
    """ValueError naming the first character of ``text`` that would not cut its own shape: a
    control or format character, or one the font has no glyph for (matplotlib would cut
    its fallback box instead). Blanks are fine: they cut nothing."""
    face = FT2Font(findfont(FontProperties(family=font)))
    for c in text:
        if c.isspace() and c in " \u00a0":
            continue
        what = None
        if unicodedata.category(c)[0] == "C" or c.isspace():
            what = "a control or layout character"
        elif face.get_char_index(ord(c)) == 0:
            what = f"not in the font {font!r}"
        if what:
            raise ValueError(f"letter_panel: text {text!r}: {c!r} (U+{ord(c):04X}) is {what}; use letters, digits "
                             "and punctuation")


def _text_layout(text, size, font_size, font):
    """Glyph geometry scaled to metres and centred on the origin of the panel."""
    w, h = size
    glyphs = _glyph_polygons(text, font)
    if glyphs.is_empty:
        raise ValueError(f"letter_panel: text {text!r} has no visible glyphs")
    _check_characters(text, font)
    x0, y0, x1, y1 = glyphs.bounds
    if font_size is None:
        # fill ~60% of the panel height with the glyphs, but keep them inside 90% of the width
        scale = min(0.6 * h / (y1 - y0), 0.9 * w / (x1 - x0))
    else:
        scale = positive(font_size, "font_size") / _TEXT_EM
    glyphs = affinity.translate(glyphs, -(x0 + x1) / 2, -(y0 + y1) / 2)
    return affinity.scale(glyphs, scale, scale, origin=(0.0, 0.0))


def letter_hole_polygons(text="ABC", size=(1.0, 0.5), font_size=None, font="DejaVu Sans"):
    """The holes cut into a :func:`letter_panel`: one shapely polygon per glyph region
    (panel frame, metres, panel centred on the origin, clipped to the panel).

    A hole is the glyph's filled shape, so the counters of "A", "O", "B" appear as the
    polygon's ``interiors`` (the island of material that stays inside the hole).
    """
    w, h = (positive(s, "letter_panel size") for s in np.broadcast_to(np.asarray(size, dtype=float), (2,)))
    glyphs = _text_layout(str(text), (w, h), font_size, font)
    glyphs = glyphs.intersection(box(-w / 2, -h / 2, w / 2, h / 2))
    return sorted(_as_polygons(glyphs), key=lambda p: p.bounds[0])


def panel_polygons(text, size, font_size, font):
    w, h = (positive(s, "letter_panel size") for s in np.broadcast_to(np.asarray(size, dtype=float), (2,)))
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


def _boundary_halfedges(faces):
    """Boundary half-edges of a triangulation (indices in face order, see
    :mod:`abmpm.geometry.topology`), sorted by the larger then the smaller vertex of
    their edge. The repairs below and the extrusion visit the edges in this order, the
    order in which letter panels have always been built, so that a given text keeps
    exactly the same triangulation and face order."""
    once = boundary_halfedges(faces)
    tail, head = halfedges(faces)
    a, b = tail[once], head[once]
    return once[np.lexsort((np.minimum(a, b), np.maximum(a, b)))]


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
    tree = cKDTree(v)  # the vertices that can lie on an edge: within its half-length of its middle
    for _ in range(len(v) + 10):
        tail, head = halfedges(faces)  # half-edge 3 f + k: edge k of face f
        once = _boundary_halfedges(faces)
        a, b = v[tail[once]], v[head[once]]
        ab = b - a
        length = np.sqrt(np.einsum("ij,ij->i", ab, ab))
        near = tree.query_ball_point(0.5 * (a + b), 0.5 * length + 2.0 * tol)
        rows = np.repeat(np.arange(len(once)), [len(c) for c in near])
        cand = np.concatenate([np.sort(c) for c in near]).astype(np.int64) if len(rows) else rows
        rel_pos = v[cand] - a[rows]
        t = np.einsum("ij,ij->i", rel_pos, ab[rows]) / length[rows] ** 2
        dist = np.abs(rel_pos[:, 0] * ab[rows, 1] - rel_pos[:, 1] * ab[rows, 0]) / length[rows]
        hit = (dist <= tol) & (t * length[rows] > tol) & ((1.0 - t) * length[rows] > tol)
        split = {}  # face -> (its edge to split, the vertex on it): the hanging vertex nearest a
        for row in np.unique(rows[hit]):
            f, k = divmod(int(once[row]), 3)
            if f in split:
                continue
            mine = hit & (rows == row)
            split[f] = (k, cand[mine][np.argmin(t[mine])])
        if not split:
            return faces
        new = []
        for f, (k, m) in split.items():
            a_, b_, c_ = faces[f, k], faces[f, (k + 1) % 3], faces[f, (k + 2) % 3]
            faces[f] = (a_, m, c_)
            new.append((m, b_, c_))
        faces = np.concatenate([faces, np.asarray(new, dtype=faces.dtype)])
    raise RuntimeError("letter panel triangulation: T-junction repair did not converge")


def triangulate_polygon(poly):
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


def extrude(v2, faces, thickness):
    """Closed prism of a CCW 2D triangulation, z in [-t/2, t/2], outward normals."""
    n = len(v2)
    h = thickness / 2
    verts = np.concatenate([np.column_stack([v2, np.full(n, -h)]), np.column_stack([v2, np.full(n, h)])])
    tail, head = halfedges(faces)
    once = _boundary_halfedges(faces)
    i, j = tail[once], head[once]  # material on the left of i -> j
    sides = np.concatenate([np.stack([i, j, j + n], 1), np.stack([i, j + n, i + n], 1)])
    return verts, np.concatenate([faces[:, ::-1], faces + n, sides])


