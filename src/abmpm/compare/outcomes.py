"""The outcome figures of a run: what each of the paper's scenes is meant to show,
measured from the particle frames (and the summary's series).

An outcome function takes ``(scene, frames, summary)`` where ``frames`` is a list of
``(time, frame_dict)`` (the arrays of :func:`abmpm.io.ply.read_particles_ply`) and
returns ``{"series": {name: [values per frame]}, "final": {name: value}}``. The
registry :data:`OUTCOMES` is keyed by scene name; scenes not in it get
:func:`generic_outcome`. The measuring helpers (``mass_beyond_plane``, ``pieces``,
``cut_gap``) work on plain arrays and are tested on synthetic particle sets.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from shapely import points as shp_points
from shapely.ops import unary_union
from shapely.prepared import prep

from abmpm.geometry.glyphs import panel_polygons
from abmpm.geometry.motion import KinematicMotion
from abmpm.geometry.procedural import _hourglass_profile
from abmpm.geometry.sampling import lattice_spacing
from abmpm.geometry.transforms import euler_matrix

Frames = list[tuple[float, dict]]

# pieces smaller than this fraction of the total mass are debris, not pieces
PIECE_MIN_MASS = 0.01


# --------------------------------------------------------------------------- measuring


def mass_beyond_plane(x: np.ndarray, mass: np.ndarray, point, normal) -> float:
    """Fraction of the mass on the side of the plane (``point``, ``normal``) that the
    normal points to."""
    d = (np.asarray(x, np.float64) - np.asarray(point, np.float64)) @ np.asarray(normal, np.float64)
    total = float(np.sum(mass))
    return float(np.sum(mass[d > 0]) / total) if total > 0 else 0.0


def link_radius(x: np.ndarray, factor: float = 1.5) -> float:
    """``factor`` times the median distance of a particle to its nearest neighbour: the
    particle spacing as the particles themselves show it (mixed levels included)."""
    if len(x) < 2:
        return 0.0
    d, _ = cKDTree(x).query(x, k=2)
    return factor * float(np.median(d[:, 1]))


Rect = tuple[np.ndarray, np.ndarray, float, float]  # centre, axes (columns: length, height, normal), length, height


def crosses_rectangles(x: np.ndarray, pairs: np.ndarray, rects: list[Rect]) -> np.ndarray:
    """Which links (pairs of particle indices) pass through one of the rectangles."""
    out = np.zeros(len(pairs), bool)
    for c, R, length, height in rects:
        a = (x[pairs[:, 0]] - c) @ R
        b = (x[pairs[:, 1]] - c) @ R
        cross = a[:, 2] * b[:, 2] < 0
        t = np.where(cross, a[:, 2] / np.where(cross, a[:, 2] - b[:, 2], 1.0), 0.0)
        hit = a[:, :2] + t[:, None] * (b[:, :2] - a[:, :2])
        out |= cross & (np.abs(hit[:, 0]) <= length / 2) & (np.abs(hit[:, 1]) <= height / 2)
    return out


def pieces(x: np.ndarray, mass: np.ndarray | None = None, radius: float | None = None,
           min_mass: float = PIECE_MIN_MASS, walls: list[Rect] = ()) -> tuple[int, np.ndarray]:
    """Connected pieces of a particle set: two particles closer than ``radius``
    (default :func:`link_radius`, 1.5 spacings) are linked, unless the link passes
    through one of the ``walls`` (a blade between them). Returns (number of pieces
    holding at least ``min_mass`` of the mass, label per particle)."""
    x = np.asarray(x, np.float64)
    n = len(x)
    if n == 0:
        return 0, np.zeros(0, int)
    mass = np.ones(n) if mass is None else np.asarray(mass, np.float64)
    r = link_radius(x) if radius is None else radius
    pairs = cKDTree(x).query_pairs(r, output_type="ndarray") if r > 0 else np.zeros((0, 2), int)
    if len(walls) and len(pairs):
        pairs = pairs[~crosses_rectangles(x, pairs, list(walls))]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    per = np.bincount(labels, weights=mass)
    return int(np.sum(per >= min_mass * mass.sum())), labels


def cut_gap(x: np.ndarray, point, normal, bin_size: float, band: float, layer: float = 0.0) -> dict:
    """Width and roughness of a cut along the plane (``point``, ``normal``).

    The particles within ``band`` of the plane are binned on the plane in squares of
    ``bin_size``; in each bin with particles on both sides, each cut face is the mean
    distance of that side's first layer of particles: those within ``layer / 2`` of the
    nearest one (``layer``: the particles' lattice spacing; 0: the nearest particle
    alone). The nearest particle alone is biased by the sampling jitter: it is the least
    of the bin's jittered draws, several independent ones in finest mode and one or two
    shared by a whole family in adaptive mode (docs/method.md, "The cut's width and the
    sampling jitter"). ``width``: median distance between the faces; ``roughness``:
    standard deviation of the face positions over the bins (mean of the two sides).
    ``bins``: bins used. No bins: width and roughness are None.
    """
    x = np.asarray(x, np.float64)
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    rel = x - np.asarray(point, np.float64)
    d = rel @ n
    near = np.abs(d) < band
    if not near.any():
        return {"width": None, "roughness": None, "bins": 0}
    keys = np.floor(np.stack([rel[near] @ u, rel[near] @ v], 1) / bin_size).astype(np.int64)
    d = d[near]
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    nb = inv.max() + 1
    pos, neg = d > 0, d <= 0
    plus = np.full(nb, np.inf)
    minus = np.full(nb, -np.inf)
    np.minimum.at(plus, inv[pos], d[pos])
    np.maximum.at(minus, inv[neg], d[neg])
    both = np.isfinite(plus) & np.isfinite(minus)
    if not both.any():
        return {"width": None, "roughness": None, "bins": 0}
    # each face: the mean of its first layer
    first = (pos & (d <= plus[inv] + 0.5 * layer)) | (neg & (d >= minus[inv] - 0.5 * layer))
    total = np.bincount(inv[first] * 2 + pos[first], d[first], minlength=2 * nb).reshape(nb, 2)
    count = np.bincount(inv[first] * 2 + pos[first], minlength=2 * nb).reshape(nb, 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        face = total / count
    plus, minus = face[both, 1], face[both, 0]
    return {
        "width": float(np.median(plus - minus)),
        "roughness": float(0.5 * (np.std(plus) + np.std(minus))),
        "bins": int(both.sum()),
    }


def swept_by(x: np.ndarray, rect: Rect, margin: float) -> np.ndarray:
    """Which points of ``x`` lie over the rectangle ``rect`` (projected along its
    normal), at least ``margin`` inside its edges: for a blade driven into a block,
    the material it has already cut through."""
    c, axes, length, height = rect
    rel = np.asarray(x, np.float64) - c
    return (np.abs(rel @ axes[:, 0]) <= 0.5 * length - margin) & (np.abs(rel @ axes[:, 1]) <= 0.5 * height - margin)


def escaped(x: np.ndarray, scene) -> int:
    """Particles that are not finite or lie outside the domain box by more than half a
    coarse cell (the walls act on the grid nodes: particles may sink a fraction of a
    cell into a wall and are pushed back)."""
    st = scene.simulation
    x = np.asarray(x, np.float64)
    finite = np.isfinite(x).all(axis=1)
    tol = 0.5 * st.dx
    lo, hi = np.asarray(st.domain_min) - tol, np.asarray(st.domain_max) + tol
    inside = np.all((x >= lo) & (x <= hi), axis=1)
    return int(np.sum(~(finite & inside)))


# --------------------------------------------------------------------------- geometry


def _collider(scene, shape: str):
    return next((c for c in scene.colliders if c.shape == shape), None)


def _plane_normal(collider, local=(0.0, 0.0, 1.0)) -> np.ndarray:
    return euler_matrix(collider.rotation) @ np.asarray(local, np.float64)


def blade_rects(collider, t: float, pad: float = 0.0) -> list[Rect]:
    """The blade(s) of a ``blade`` or ``crossed_plates`` collider at time ``t`` as
    rectangles (its motion applied), grown by ``pad`` on every side."""
    pose = KinematicMotion(collider.motion, collider.center).pose(t)
    c = pose.rotation @ np.asarray(collider.center, np.float64) + pose.offset
    R0 = pose.rotation @ euler_matrix(collider.rotation)
    if collider.shape == "blade":
        return [(c, R0, collider.length + 2 * pad, collider.height + 2 * pad)]
    length, height = collider.size
    return [(c, R0 @ euler_matrix((0.0, a, 0.0)), length + 2 * pad, height + 2 * pad) for a in (45.0, -45.0)]


def _far_side(scene, frames: Frames, point, normal) -> np.ndarray:
    """The normal of the plane turned to point away from where the material starts."""
    _, f0 = frames[0]
    side = (np.average(f0["x"], axis=0, weights=f0["mass"]) - point) @ normal
    return -normal if side > 0 else normal


def _hourglass_radius(collider):
    """World y -> inner radius of the glass (None outside its height)."""
    prof = _hourglass_profile(collider.height, collider.radius, collider.neck_radius, 400)
    y0 = collider.center[1] - collider.height / 2

    def radius(y):
        y = np.asarray(y, np.float64) - y0
        return np.where((y >= 0) & (y <= collider.height), np.interp(y, prof[:, 1], prof[:, 0]), np.nan)

    return radius


def _panel_material(collider):
    """The solid part of a letter panel (shapely), in the panel's own xy coordinates."""
    return unary_union(panel_polygons(collider.text, collider.size, None, "DejaVu Sans"))


# A particle's path between two output frames is taken to be at most this many
# times its straight displacement. A crossing whose straight line meets the panel's
# material is a leak only if no path through an opening is that short: a fast
# particle that slid sideways into a letter and through it crosses the plane, on the
# straight line, over material (at paper scale, 2-7 cm per frame against 1 cm
# margins; such passes needed at most 1.21 times the straight line, the particles
# that really went through a sheet 3.3-3.8 times).
PANEL_DETOUR = 1.5


def panel_crossings_through_material(scene, frames: Frames, margin: float) -> int:
    """Particles (followed by id between consecutive frames) that changed side of the
    letter panel at a point of the panel's material farther than ``margin`` from any
    hole or the panel's edge, and that no path through an opening at most
    ``PANEL_DETOUR`` times their displacement explains: they went through the solid
    panel."""
    col = _collider(scene, "letter_panel")
    if col is None or len(frames) < 2:
        return 0
    R = euler_matrix(col.rotation)
    c = np.asarray(col.center, np.float64)
    material = _panel_material(col)
    solid = prep(material.buffer(-margin))
    st = scene.simulation
    rims = _opening_rims(material, 0.25 * margin, lambda q: q @ R.T + c, (st.domain_min, st.domain_max), margin)
    count = 0
    for (_, a), (_, b) in zip(frames, frames[1:]):
        ida, idb = a["id"], b["id"]
        common, ia, ib = np.intersect1d(ida, idb, return_indices=True)
        if len(common) == 0:
            continue
        pa = (a["x"][ia] - c) @ R
        pb = (b["x"][ib] - c) @ R
        crossed = np.sign(pa[:, 2]) * np.sign(pb[:, 2]) < 0
        if not crossed.any():
            continue
        pa, pb = pa[crossed], pb[crossed]
        t = pa[:, 2] / (pa[:, 2] - pb[:, 2])
        hit = pa[:, :2] + t[:, None] * (pb[:, :2] - pa[:, :2])
        over = np.array([solid.contains(p) for p in shp_points(hit)], dtype=bool)
        for A, B in zip(pa[over], pb[over]):
            shortest = (np.linalg.norm(rims - A, axis=1) + np.linalg.norm(rims - B, axis=1)).min() if len(rims) \
                else np.inf
            count += int(shortest > PANEL_DETOUR * np.linalg.norm(B - A))
    return count


def _opening_rims(material, spacing: float, to_world, walls, margin: float) -> np.ndarray:
    # points every ``spacing`` along the rims of the holes, and along the panel's
    # outline where it leaves a gap to the domain's walls, on the panel's plane (local
    # z = 0): a path through an opening is shortest across a rim
    polys = [material] if material.geom_type == "Polygon" else list(material.geoms)
    lo, hi = (np.asarray(w, np.float64) for w in walls)
    pts = []
    for poly in polys:
        for ring, outline in [(poly.exterior, True), *((r, False) for r in poly.interiors)]:
            xy = np.array([ring.interpolate(d).coords[0][:2] for d in np.arange(0.0, ring.length, spacing)])
            local = np.column_stack([xy, np.zeros(len(xy))])
            if outline:  # closed off where it lies against a wall
                w = to_world(local)
                local = local[np.minimum(w - lo, hi - w).min(axis=1) > margin]
            pts.append(local)
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def hourglass_outside(scene, x: np.ndarray, margin: float, ids=None, exclude=()) -> int:
    """Particles within the glass's height and farther than ``margin`` outside its wall,
    leaving out those whose id is in ``exclude``."""
    col = _collider(scene, "hourglass")
    if col is None:
        return 0
    r_of = _hourglass_radius(col)
    x = np.asarray(x, np.float64)
    r = np.hypot(x[:, 0] - col.center[0], x[:, 2] - col.center[2])
    wall = r_of(x[:, 1])
    out = np.isfinite(wall) & (r > wall + margin)
    if ids is not None and len(exclude):
        out &= ~np.isin(ids, np.asarray(list(exclude)))
    return int(np.sum(out))


def over_the_mouth(scene, frames: Frames) -> set:
    """Ids of the particles that were above the hourglass's open mouth in some frame
    (splashed out of the top: outside the glass afterwards, but not through it)."""
    col = _collider(scene, "hourglass")
    top = col.center[1] + col.height / 2
    seen: set = set()
    for _, f in frames:
        seen.update(np.asarray(f["id"])[np.asarray(f["x"])[:, 1] > top].tolist())
    return seen


# --------------------------------------------------------------------------- outcomes


def _times(frames: Frames) -> list[float]:
    return [round(float(t), 6) for t, _ in frames]


def _kinetic(summary: dict) -> dict:
    s = (summary or {}).get("series") or {}
    return {"time": s.get("time") or [], "kinetic_energy": s.get("kinetic_energy") or []}


def panel_outcome(scene, frames: Frames, summary: dict) -> dict:
    col = _collider(scene, "letter_panel")
    c = np.asarray(col.center, np.float64)
    n = _far_side(scene, frames, c, _plane_normal(col))
    through = [mass_beyond_plane(f["x"], f["mass"], c, n) for _, f in frames]
    return {"series": {"time": _times(frames), "mass_through": through},
            "final": {"mass_through": through[-1]}}


def hourglass_outcome(scene, frames: Frames, summary: dict) -> dict:
    col = _collider(scene, "hourglass")
    c = np.asarray(col.center, np.float64)
    below = [mass_beyond_plane(f["x"], f["mass"], c, (0.0, -1.0, 0.0)) for _, f in frames]
    return {"series": {"time": _times(frames), "mass_below_neck": below},
            "final": {"mass_below_neck": below[-1]}}


def cut_outcome(scene, frames: Frames, summary: dict) -> dict:
    col = _collider(scene, "blade")
    t, f = frames[-1]
    rects = blade_rects(col, t)
    c, n = rects[0][0], rects[0][1][:, 2]
    st = scene.simulation
    # the cut is where the blade has been: below its edge the block is whole and the
    # "gap" would be the particle spacing of whatever level samples it; the last coarse
    # cell above the edge is still being split. Bins as fine as the fine grid: the cut
    # is a fine-grid feature, and a coarse bin mixes the faces with the groove that the
    # blade drags into the top surface (paper scale, 0.2 s after contact, faces by the
    # nearest particle: finest read 9.9 mm with fine bins and 7.7 or 22.5 mm with coarse
    # ones, by where the bins fall)
    cut = swept_by(f["x"], rects[0], margin=st.dx)
    fine = st.dx / st.refinement.factor
    layer = lattice_spacing(fine, scene.bodies[0].particles_per_cell)  # the finest level's particle spacing
    gap = cut_gap(np.asarray(f["x"])[cut], c, n, bin_size=fine, band=2.0 * st.dx, layer=layer)
    # a blade whose edge has reached the floor still has a film of material under it
    # (particles sink a fraction of a cell into a wall): grow it by half a cell
    count, _ = pieces(f["x"], f["mass"], walls=blade_rects(col, t, pad=0.5 * st.dx))
    return {"series": {}, "final": {
        "cut_width": gap["width"], "cut_roughness": gap["roughness"], "cut_bins": gap["bins"],
        "pieces": count, "mass_beyond_blade": mass_beyond_plane(f["x"], f["mass"], c, n),
    }}


def bunny_split_outcome(scene, frames: Frames, summary: dict) -> dict:
    col = _collider(scene, "crossed_plates")
    R = euler_matrix(col.rotation)
    n1 = R @ euler_matrix((0.0, 45.0, 0.0)) @ np.array([0.0, 0.0, 1.0])
    n2 = R @ euler_matrix((0.0, -45.0, 0.0)) @ np.array([0.0, 0.0, 1.0])
    t, f = frames[-1]
    d = np.asarray(f["x"], np.float64) - np.asarray(col.center)
    s1, s2 = d @ n1 > 0, d @ n2 > 0
    m = np.asarray(f["mass"], np.float64)
    total = m.sum()
    quarters = [float(m[(s1 == a) & (s2 == b)].sum() / total) for a in (True, False) for b in (True, False)]
    count, _ = pieces(f["x"], f["mass"], walls=blade_rects(col, t, pad=0.5 * scene.simulation.dx))
    return {"series": {}, "final": {"mass_per_quarter": quarters, "pieces": count}}


def jelly_outcome(scene, frames: Frames, summary: dict) -> dict:
    ke = _kinetic(summary)
    peak = max(ke["kinetic_energy"]) if ke["kinetic_energy"] else None
    return {"series": ke, "final": {"kinetic_energy_peak": peak,
                                    "kinetic_energy_end": ke["kinetic_energy"][-1] if ke["kinetic_energy"] else None}}


def generic_outcome(scene, frames: Frames, summary: dict) -> dict:
    st = scene.simulation
    mid = 0.5 * (st.domain_min[1] + st.domain_max[1])
    below = [mass_beyond_plane(f["x"], f["mass"], (0.0, mid, 0.0), (0.0, -1.0, 0.0)) for _, f in frames]
    ke = _kinetic(summary)
    return {"series": {"time": _times(frames), "mass_below_mid_height": below, **{"ke_" + k: v for k, v in ke.items()}},
            "final": {"mass_below_mid_height": below[-1] if below else None}}


OUTCOMES: dict[str, Callable] = {
    "paper_panel": panel_outcome,
    "letter_panel": panel_outcome,
    "paper_hourglass": hourglass_outcome,
    "hourglass": hourglass_outcome,
    "paper_cut": cut_outcome,
    "blade_cut": cut_outcome,
    "paper_bunny_split": bunny_split_outcome,
    "paper_jelly": jelly_outcome,
    "jelly_drop": jelly_outcome,
}

# the series each scene plots against time (None: no time plot)
PLOTTED = {panel_outcome: "mass_through", hourglass_outcome: "mass_below_neck",
           jelly_outcome: "kinetic_energy", generic_outcome: "mass_below_mid_height"}


def outcome_for(scene) -> Callable:
    fn = OUTCOMES.get(scene.name, generic_outcome)
    needs = {panel_outcome: "letter_panel", hourglass_outcome: "hourglass", cut_outcome: "blade",
             bunny_split_outcome: "crossed_plates"}.get(fn)
    if needs and _collider(scene, needs) is None:  # renamed scene without the collider
        return generic_outcome
    return fn


def leaks(scene, frames: Frames) -> dict:
    """Leaked particles of a run (must all be 0):

    * ``escaped``: particles of the last frame that are not finite or outside the domain;
    * ``through_panel`` (scenes with a letter panel): particles that crossed the panel's
      plane, between two consecutive output frames, at a point of its material more than
      one coarse cell from any hole or edge (followed by id; split children, which get
      new ids, are followed from the frame after their split);
    * ``outside_glass`` (scenes with an hourglass): particles of the last frame more than
      one coarse cell outside the glass wall, within its height, except those that were
      above the open mouth in some output frame (they splashed out of the top; their
      number is ``over_the_mouth``, not counted in ``total``).
    """
    dx = scene.simulation.dx
    _, last = frames[-1]
    out = {"escaped": escaped(last["x"], scene)}
    if _collider(scene, "letter_panel") is not None:
        out["through_panel"] = panel_crossings_through_material(scene, frames, margin=dx)
    splashed = 0
    if _collider(scene, "hourglass") is not None:
        over = over_the_mouth(scene, frames)
        out["outside_glass"] = hourglass_outside(scene, last["x"], margin=dx, ids=last.get("id"), exclude=over)
        splashed = len(over)
    out["total"] = int(sum(v for v in out.values()))
    if splashed:
        out["over_the_mouth"] = splashed  # not a leak: left through the open top
    return out

