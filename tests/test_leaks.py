"""No particle ever changes sides of a collider (CPIC, paper Eq. 21), whatever the
collider's winding, the side the material comes from, the angle or the speed.

The matrix: every collider kind x both windings (the procedural mesh as built, and
the same triangles reversed, read from a mesh file) x material on either side x
two impact speeds (3 and 15 m/s), tilted at angles not aligned with the grid, with
gravity pressing the material onto the surface for 1.2 s so that it slides along
it into a corner with a domain wall. After EVERY substep each particle's side is
measured by geometry computed here, independently of the solver (float64, from the
collider's own vertices), and compared with the side it started on.

The geometry of each case is chosen so that there is no legitimate way to the other
side (sheets span the domain; the funnel and the hourglass reach through the floor
and the ceiling; the closed mesh is closed), except the letter panel, whose holes
are a legitimate way through: there a particle may change sides only where its step
crosses the panel's plane inside a hole.
"""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import trimesh
from shapely.geometry import LineString, Polygon

import abmpm
from abmpm.geometry.placement import collider_mesh
from abmpm.geometry.transforms import euler_matrix
from abmpm.scene import model as sm

DX = 0.03
L = 0.6  # domain edge, m
C = np.array([0.3, 0.3, 0.3])
SECONDS = 1.2
TILT = (13.0, 0.0, 27.0)  # XYZ Euler degrees of the planar colliders
TILT_REV = (7.0, 0.0, 5.0)  # of the surfaces of revolution (axis stays near vertical)
G = 9.81


def water():
    return abmpm.Fluid(name="water", bulk_modulus=1e5, viscosity=0.01)


def planar_normal(rotation, local=(0.0, 1.0, 0.0)):
    return euler_matrix(rotation) @ np.asarray(local)


# --------------------------------------------------------------------------- side measures
# Each returns, for positions x (N, 3), +1 / -1 for the two sides, and 0 where the
# side cannot be told within the stated geometric tolerance (never counted as wrong).


class PlaneSide:
    """Sign of the distance to the plane through C with normal n. The sheets span the
    whole domain, so this is the collider's side exactly. ``half`` > 0: a closed plate
    of that half thickness, inside which a particle is on the wrong side of both."""

    def __init__(self, n, half=0.0):
        self.n, self.half = np.asarray(n, float), half

    def __call__(self, x):
        d = (x.astype(np.float64) - C) @ self.n
        return np.where(d > self.half, 1, np.where(d < -self.half, -1, 2))  # 2: inside the plate


class RevolutionSide:
    """Inside (+1) / outside (-1) of a surface of revolution about the collider's axis,
    from the (r, y) profile read off its own vertices. Faceting: the mesh has
    ``segments`` sides, so between rings it lies up to r_max (1 - cos(pi/segments))
    inside the true revolved profile; particles closer to the profile than that (plus
    1e-6 m round-off) are undecided."""

    def __init__(self, mesh, center, rotation, segments=64):
        self.R = euler_matrix(rotation)
        self.c = np.asarray(center, float)
        q = (np.asarray(mesh.vertices) - self.c) @ self.R
        r, y = np.hypot(q[:, 0], q[:, 2]), q[:, 1]
        rows = np.unique(np.round(y, 9))
        prof = np.array([(r[np.abs(y - yy) < 1e-7].max(), yy) for yy in rows])
        self.line = LineString(prof)
        ring = [(0.0, prof[0, 1])] + [tuple(p) for p in prof] + [(0.0, prof[-1, 1])]
        self.inside = Polygon(ring)
        self.tol = prof[:, 0].max() * (1.0 - np.cos(np.pi / segments)) + 1e-6
        shapely.prepare(self.line)  # indexed once: the tests ask after every step, for every particle
        shapely.prepare(self.inside)

    def __call__(self, x):
        q = (x.astype(np.float64) - self.c) @ self.R
        r, y = np.hypot(q[:, 0], q[:, 2]), q[:, 1]
        pts = shapely.points(r, y)
        far = ~shapely.dwithin(self.line, pts, self.tol)  # distance > tol
        inside = shapely.contains(self.inside, pts)
        return np.where(far, np.where(inside, 1, -1), 0)


class SphereSide:
    """Outside (+1) / inside (-1) of a closed convex polyhedron inscribed in a sphere
    of radius R: outside is certain beyond R, inside within the inradius."""

    def __init__(self, mesh):
        v = np.asarray(mesh.vertices) - C
        self.R = np.linalg.norm(v, axis=1).max()
        n = np.asarray(mesh.face_normals)
        self.r_in = np.abs(np.einsum("ij,ij->i", n, v[mesh.faces[:, 0]])).min()

    def __call__(self, x):
        d = np.linalg.norm(x.astype(np.float64) - C, axis=1)
        return np.where(d > self.R, 1, np.where(d < self.r_in, -1, 0))


# --------------------------------------------------------------------------- the cases


def reversed_file(spec, tmp_path):
    """The collider's world mesh with every triangle reversed, as a mesh file."""
    mesh = collider_mesh(spec)
    flipped = trimesh.Trimesh(mesh.vertices, np.asarray(mesh.faces)[:, ::-1], process=False)
    path = tmp_path / f"{spec.shape}_reversed.ply"
    flipped.export(path)
    return sm.MeshCollider(file=path, boundary=spec.boundary), mesh


def planar_case(kind, side, speed):
    """Material on ``side`` (+1: the side the normal points to) of a tilted plane
    through C, thrown at it, pressed onto it by gravity along -side n tilted 30 deg
    off the normal so that it slides down into the corner with a wall."""
    if kind == "sheet":
        spec = sm.SheetCollider(size=(2.0, 2.0), center=tuple(C), rotation=TILT)
        n, half = planar_normal(TILT), 0.0
    elif kind == "thin_box":
        spec = sm.ThinBoxCollider(size=(2.0, 0.003, 2.0), center=tuple(C), rotation=TILT)  # 0.1 dx thick
        n, half = planar_normal(TILT), 0.0015
    elif kind == "blade":
        spec = sm.BladeCollider(length=2.0, height=2.0, center=tuple(C), rotation=TILT)
        n, half = planar_normal(TILT, (0.0, 0.0, 1.0)), 0.0
    else:
        raise ValueError(kind)
    return (spec, *thrown_at_plane(n, side, speed), PlaneSide(n, half))


def thrown_at_plane(n, side, speed):
    """Water on ``side`` of the plane through C with normal n, thrown at it, and
    gravity along -side n tilted 30 deg so that the water slides into a corner."""
    t = np.cross(n, [0.0, 0.0, 1.0])
    t /= np.linalg.norm(t)
    gravity = -side * G * (np.cos(np.radians(30)) * n + np.sin(np.radians(30)) * t)
    body = sm.SphereBody(material="water", center=tuple(C + side * 0.14 * n), radius=0.09,
                         velocity=tuple(-side * speed * n))
    return body, gravity


def revolution_case(kind, side, speed):
    """+1: material inside the funnel / hourglass; -1: outside, against its wall."""
    if kind == "funnel":
        # pipe through the floor, cone mouth above the ceiling: no way round
        spec = sm.FunnelCollider(top_radius=0.26, pipe_radius=0.07, cone_height=0.5, pipe_length=0.3,
                                 center=(0.3, 0.26, 0.3), rotation=TILT_REV)
        inside_c, outside_c = (0.3, 0.42, 0.3), (0.3, 0.1, 0.12)
        gravity_in, gravity_out = (0.0, -G, 0.0), (0.0, G, 0.0)  # outside: pressed up under the cone
    elif kind == "hourglass":
        # bulbs of 0.25 m, neck 0.05 m, mouth above the ceiling
        spec = sm.HourglassCollider(height=0.84, radius=0.25, neck_radius=0.05, center=(0.3, 0.3, 0.3),
                                    rotation=TILT_REV)
        inside_c, outside_c = (0.3, 0.48, 0.3), (0.08, 0.3, 0.08)
        gravity_in, gravity_out = (0.0, -G, 0.0), (G * 0.6, 0.0, G * 0.6)  # outside: pressed into the neck
    else:
        raise ValueError(kind)
    centre = np.array(inside_c if side > 0 else outside_c)
    axis_pt = C + (centre - C)[1] * planar_normal(TILT_REV)
    radial = centre - axis_pt
    radial[1] = 0.0
    radial = radial / max(np.linalg.norm(radial), 1e-9)
    if side > 0:
        v = speed * np.array([0.0, -1.0, 0.0])  # straight down into the bulb / cone
        gravity = gravity_in
    else:
        v = -speed * radial  # at the wall from outside
        gravity = gravity_out
    body = sm.SphereBody(material="water", center=tuple(centre), radius=0.06, velocity=tuple(v))
    return spec, body, np.array(gravity), None


def closed_mesh_case(side, speed, tmp_path):
    """A closed icosphere from a file; +1 material outside thrown at it, -1 inside it."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.16)
    path = tmp_path / "ball.obj"
    sphere.export(path)
    spec = sm.MeshCollider(file=path, center=tuple(C))
    if side > 0:
        body = sm.SphereBody(material="water", center=(0.3, 0.53, 0.3), radius=0.06, velocity=(0.0, -speed, 0.0))
        gravity = (0.0, -G, 0.0)
    else:
        body = sm.SphereBody(material="water", center=(0.3, 0.3, 0.3), radius=0.08, velocity=(speed, 0.0, 0.0))
        gravity = (0.0, -G, 0.0)
    return spec, body, np.array(gravity), None


class PanelCrossing:
    """A zero-thickness panel with holes (letters): a particle may go to the other
    side only through a hole. A step moves a particle along a straight segment (the
    solver's advection), so a particle crossed the panel exactly when its segment
    meets the panel's plane at a point of the panel's material. The material is the
    union of the panel's own triangles, in its plane; points closer than 1e-6 m
    (about 30 float32 ulps at 0.5 m) to a hole's edge are undecided."""

    def __init__(self, mesh, center, rotation):
        self.R = euler_matrix(rotation)
        self.c = np.asarray(center, float)
        q = (np.asarray(mesh.vertices) - self.c) @ self.R
        assert np.abs(q[:, 2]).max() < 1e-9  # the panel lies in its local xy-plane
        tris = [Polygon(q[f, :2]) for f in np.asarray(mesh.faces)]
        self.material = shapely.union_all([t for t in tris if t.area > 0]).buffer(-1e-6)

    def __call__(self, x_old, x_new):
        a = (x_old.astype(np.float64) - self.c) @ self.R
        b = (x_new.astype(np.float64) - self.c) @ self.R
        cross = np.nonzero(a[:, 2] * b[:, 2] < 0.0)[0]
        if len(cross) == 0:
            return 0
        t = a[cross, 2] / (a[cross, 2] - b[cross, 2])
        hit = a[cross, :2] + t[:, None] * (b[cross, :2] - a[cross, :2])
        return int(shapely.contains_xy(self.material, hit[:, 0], hit[:, 1]).sum())


def run_watched(spec, body, gravity, side_of, seconds=SECONDS, mode="original", crossing=None, factor=2,
                coupling="overlap"):
    """Run the scene; after every substep count the particles on the wrong side
    (``side_of``: against the side they, or the parent they were split from, started
    on) or that crossed the collider in that step (``crossing``).
    Returns (worst count, steps, particles at the end, particles split)."""
    # adaptive: a box around the impact is refined (keeps the fine grid, and the test, small)
    refinement = sm.Refinement(mode=mode, factor=factor, boxes=[(tuple(C - 0.15), tuple(C + 0.15))],
                               coupling=coupling)
    spec = spec.model_copy(update={"refine": False})
    scene = abmpm.Scene(
        simulation=abmpm.SimulationSettings(domain_max=(L, L, L), dx=DX, gravity=tuple(float(g) for g in gravity),
                                            fps=10, refinement=refinement),
        materials=[water()], bodies=[body], colliders=[spec],
    )
    sim = abmpm.Simulation(scene, device="cpu")
    p = sim.particles()
    # indexed by particle id (split children get the next free ids)
    x_old = np.zeros((p.id.max() + 1, 3))
    x_old[p.id] = p.x
    start = np.zeros(len(x_old), dtype=int)
    if side_of is not None:
        start[p.id] = side_of(p.x)
        assert len(np.unique(start[p.id])) == 1  # all start on one side (also any children split at t = 0)
        # a family split at t = 0 that merges back takes its parent's id: its side too
        kids = p.family >= 0
        start[p.family[kids]] = start[p.id[kids]]
        x_old[p.family[kids]] = p.x[kids]
    worst, steps, split = 0, 0, 0
    while sim.time < seconds - 1e-9:
        sim.step()
        steps += 1
        p = sim.particles()
        if p.id.max() >= len(x_old):  # a split child starts where its parent was, on its side
            grow = p.id.max() + 1 - len(x_old)
            x_old = np.concatenate([x_old, np.zeros((grow, 3))])
            start = np.concatenate([start, np.zeros(grow, dtype=int)])
            new = p.family >= 0
            new &= p.id >= len(x_old) - grow
            split += int(new.sum())
            x_old[p.id[new]] = x_old[p.family[new]]
            start[p.id[new]] = start[p.family[new]]
        if crossing is not None:
            worst = max(worst, crossing(x_old[p.id], p.x))
        else:
            now = side_of(p.x)
            worst = max(worst, int(((now != start[p.id]) & (now != 0)).sum()))
        x_old[p.id] = p.x
    return worst, steps, len(p), split


# --------------------------------------------------------------------------- tests

SPEEDS = [3.0, 15.0]
SIDES = [1, -1]
WINDINGS = ["as-built", "reversed"]


def _case(kind, side, speed, winding, tmp_path):
    if kind in ("sheet", "thin_box", "blade"):
        spec, body, gravity, side_of = planar_case(kind, side, speed)
    elif kind in ("funnel", "hourglass"):
        spec, body, gravity, side_of = revolution_case(kind, side, speed)
    else:
        spec, body, gravity, side_of = closed_mesh_case(side, speed, tmp_path)
    mesh = collider_mesh(spec, resolve=lambda p: p)
    if side_of is None:
        side_of = SphereSide(mesh) if kind == "mesh_closed" else RevolutionSide(mesh, spec.center, TILT_REV)
    if winding == "reversed":
        spec, _ = reversed_file(spec, tmp_path)
    return spec, body, gravity, side_of


@pytest.mark.parametrize("speed", SPEEDS, ids=lambda s: f"{s:g}mps")
@pytest.mark.parametrize("side", SIDES, ids=["front", "back"])
@pytest.mark.parametrize("winding", WINDINGS)
@pytest.mark.parametrize("kind", ["sheet", "thin_box", "blade", "funnel", "hourglass", "mesh_closed"])
def test_no_particle_changes_sides(kind, winding, side, speed, tmp_path):
    spec, body, gravity, side_of = _case(kind, side, speed, winding, tmp_path)
    start = side_of(abmpm.Simulation(abmpm.Scene(
        simulation=abmpm.SimulationSettings(domain_max=(L, L, L), dx=DX), materials=[water()], bodies=[body]),
        device="cpu").particles().x)
    # the case is what it says: every particle starts clearly on the intended side
    # (+1: the plane's normal side, inside the funnel / hourglass, outside the ball)
    assert np.all(start == side), np.unique(start, return_counts=True)
    worst, steps, n, _ = run_watched(spec, body, gravity, side_of)
    assert worst == 0, f"{worst} of {n} particles on the wrong side (checked after each of {steps} steps)"


def letter_panel_case(side, speed):
    spec = sm.LetterPanelCollider(text="HI", size=(1.0, 0.6), center=tuple(C), rotation=TILT)
    return (spec, *thrown_at_plane(planar_normal(TILT, (0.0, 0.0, 1.0)), side, speed))


@pytest.mark.parametrize("speed", SPEEDS, ids=lambda s: f"{s:g}mps")
@pytest.mark.parametrize("side", SIDES, ids=["front", "back"])
@pytest.mark.parametrize("winding", WINDINGS)
def test_letter_panel_is_crossed_only_through_its_holes(winding, side, speed, tmp_path):
    spec, body, gravity = letter_panel_case(side, speed)
    crossing = PanelCrossing(collider_mesh(spec), spec.center, TILT)
    if winding == "reversed":
        spec, _ = reversed_file(spec, tmp_path)
    worst, steps, n, _ = run_watched(spec, body, gravity, None, crossing=crossing)
    assert worst == 0, f"{worst} of {n} particles crossed the panel outside its holes in one of {steps} steps"


@pytest.mark.parametrize("case", ["sheet-back", "thin_box-front", "letter_panel-back", "hourglass-inside",
                                  "letter_panel-back-3", "hourglass-inside-3", "letter_panel-back-2-partition"])
def test_split_particles_stay_on_their_side(case, tmp_path):
    """Adaptive mode: the particles are split next to the surface (Eq. 15); no child
    may land on, or later move to, the other side of its parent. At b = 3 (the cases
    ending in 3): in the hourglass, level-0 particles in the glass's band move with the
    fine grid (docs/method.md), up to 11 at a time; on the letter panel one level-1
    particle crossed next to a letter's edge until ``stop_crossing`` cast the
    particle's own path as well as the ray from its backed-off start. With the partition
    coupling (the case ending in partition) each particle reaches both grids' nodes in the
    band, each grid's masked by its own colors (sim/partition_transfers.py); its sheet case
    passed too (35 s, not in the suite)."""
    kind, where, *factor = case.split("-")
    coupling = factor.pop() if factor and factor[-1] == "partition" else "overlap"
    side = 1 if where in ("front", "inside") else -1
    crossing = side_of = None
    if kind == "letter_panel":
        spec, body, gravity = letter_panel_case(side, 15.0)
        crossing = PanelCrossing(collider_mesh(spec), spec.center, TILT)
    else:
        spec, body, gravity, side_of = _case(kind, side, 15.0, "reversed", tmp_path)
    worst, steps, n, split = run_watched(spec, body, gravity, side_of, seconds=0.15, mode="adaptive",
                                         crossing=crossing, factor=int(factor[0]) if factor else 2, coupling=coupling)
    assert split > 0  # the case splits particles near the surface
    assert worst == 0, f"{worst} of {n} particles on the wrong side (after each of {steps} steps)"


@pytest.mark.parametrize("side", SIDES, ids=["pushes-front", "pushes-back"])
@pytest.mark.parametrize("winding", WINDINGS)
def test_moving_sheet_squeezes_water_into_a_corner_without_a_leak(winding, side, tmp_path):
    """A tilted sheet spanning the domain moves 0.2 m in 0.6 s and pushes water into
    the corner it makes with the floor and a wall, with either face leading; the water
    is then held there for another 0.6 s. The side is measured against the sheet's
    position at the time of each check."""
    rot = (8.0, 0.0, -81.0)  # normal close to +x, off the grid axes
    n = planar_normal(rot)
    c0 = C - side * 0.15 * n
    travel = side * 0.2 * n
    spec = sm.SheetCollider(size=(2.0, 2.0), center=tuple(c0), rotation=rot, motion=sm.Motion(keyframes=[
        sm.Keyframe(time=0.0), sm.Keyframe(time=0.6, translation=tuple(travel))]))
    if winding == "reversed":
        flipped, _ = reversed_file(spec, tmp_path)
        spec = flipped.model_copy(update={"motion": spec.motion})
    body = sm.SphereBody(material="water", center=tuple(C + side * 0.12 * n), radius=0.08)

    def centre(t):
        return c0 + travel * min(t / 0.6, 1.0)

    scene = abmpm.Scene(simulation=abmpm.SimulationSettings(domain_max=(L, L, L), dx=DX, fps=10),
                        materials=[water()], bodies=[body], colliders=[spec])
    sim = abmpm.Simulation(scene, device="cpu")
    side0 = np.sign((sim.particles().x - centre(0.0)) @ n)
    assert np.all(side0 == side)
    worst = 0
    while sim.time < SECONDS - 1e-9:
        sim.step()
        d = (sim.particles().x - centre(sim.time)) @ n
        worst = max(worst, int((np.sign(d) != side).sum()))
    assert worst == 0, f"{worst} particles behind the moving sheet"


def test_builtin_hourglass_keeps_all_its_water():
    """The built-in hourglass in original mode (the audit saw 0.3% of its water, 7 of
    2176 particles, end outside the glass after 1.5 s): every frame, no particle is
    outside the glass."""
    scene = abmpm.load_scene("hourglass")
    glass = scene.colliders[0]
    side_of = RevolutionSide(collider_mesh(glass), glass.center, glass.rotation)
    sim = abmpm.Simulation(scene, device="cpu", mode="original")
    assert np.all(side_of(sim.particles().x) == 1)
    outside = []
    sim.advance(seconds=scene.simulation.duration,
                callback=lambda s: outside.append(int((side_of(s.particles().x) == -1).sum())))
    assert max(outside) == 0, outside
