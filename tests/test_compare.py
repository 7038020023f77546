"""abmpm.compare: outcome figures on synthetic particles, a tiny comparison run, the
paper scenes and their quick versions, and the CLI's errors."""

import json
import re

import numpy as np
import pytest

from abmpm.cli import main
from abmpm.compare import (
    MODES,
    PAPER_CONTACT,
    PAPER_SCENES,
    PAPER_TABLE1,
    QUICK_OVERRIDES,
    apply_overrides,
    compare,
    quick_scene,
    remeasure,
)
from abmpm.compare.core import window_figures, window_frames
from abmpm.compare.outcomes import (
    cut_gap,
    swept_by,
    escaped,
    hourglass_outside,
    mass_beyond_plane,
    panel_crossings_through_material,
    pieces,
)
from abmpm.geometry.transforms import euler_matrix
from abmpm.scene.loader import load_scene
from abmpm.scene.model import BoxBody, Elastic, Scene, SimulationSettings, with_mode


def _block(lo, hi, h):
    axes = [np.arange(a + h / 2, b, h) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


# --------------------------------------------------------------------------- measuring


def test_mass_beyond_plane():
    x = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    m = np.array([1.0, 1.0, 1.0, 5.0])
    assert mass_beyond_plane(x, m, (1.5, 0, 0), (1, 0, 0)) == pytest.approx(6 / 8)
    assert mass_beyond_plane(x, m, (1.5, 0, 0), (-1, 0, 0)) == pytest.approx(2 / 8)


def test_pieces_counts_separate_blocks_and_ignores_debris():
    h = 0.01
    a = _block((0, 0, 0), (0.1, 0.1, 0.1), h)
    b = _block((0.2, 0, 0), (0.3, 0.1, 0.1), h)
    assert pieces(a)[0] == 1
    x = np.concatenate([a, b, [[0.5, 0.5, 0.5]]])  # one stray particle: debris, not a piece
    n, labels = pieces(x)
    assert n == 2
    assert len(set(labels[: len(a)])) == 1 and labels[0] != labels[len(a)]
    # blocks closer than 1.5 spacings are one piece
    c = _block((0.1 + h / 4, 0, 0), (0.2, 0.1, 0.1), h)  # 1.25 spacings apart
    assert pieces(np.concatenate([a, c]))[0] == 1


def test_pieces_cut_by_a_blade_between_them():
    h = 0.01
    a = _block((0, 0, 0), (0.1, 0.1, 0.1), h)
    b = _block((0.1, 0, 0), (0.2, 0.1, 0.1), h)  # touching: one piece
    x = np.concatenate([a, b])
    assert pieces(x)[0] == 1
    blade = (np.array([0.1, 0.05, 0.05]), euler_matrix((0.0, 90.0, 0.0)), 0.2, 0.2)  # the plane x = 0.1
    assert pieces(x, walls=[blade])[0] == 2
    short = (np.array([0.1, 0.1, 0.05]), euler_matrix((0.0, 90.0, 0.0)), 0.2, 0.08)  # reaches y = 0.06 only
    assert pieces(x, walls=[short])[0] == 1


def test_cut_gap_width_and_roughness():
    h = 0.01
    left = _block((-0.2, 0, 0), (-0.05, 0.1, 0.1), h)   # last layer at x = -0.055
    right = _block((0.05, 0, 0), (0.2, 0.1, 0.1), h)    # first layer at x = 0.055
    x = np.concatenate([left, right])
    g = cut_gap(x, (0, 0, 0), (1, 0, 0), bin_size=0.02, band=0.1)
    assert g["width"] == pytest.approx(0.11)
    assert g["roughness"] == pytest.approx(0.0, abs=1e-12)
    assert g["bins"] == 25
    # a jagged face: every other bin of the right face one layer deeper
    jag = right[~((right[:, 0] < 0.06) & (np.floor(right[:, 1] / 0.02) % 2 == 0))]
    g2 = cut_gap(np.concatenate([left, jag]), (0, 0, 0), (1, 0, 0), bin_size=0.02, band=0.1)
    assert g2["roughness"] > 0.001
    # nothing on one side: no cut measured
    assert cut_gap(left, (0, 0, 0), (1, 0, 0), 0.02, 0.1)["width"] is None


def test_cut_faces_do_not_depend_on_how_the_particles_were_jittered():
    """Two blocks whose facing layers lie 2h apart (h = 0.01 the lattice spacing), sampled
    with the jitter of finest mode (each particle on its own, up to h/4 per axis) and of
    adaptive mode (a family of 3x3x3 children shifted together). The nearest particle per
    bin is the least of the bin's four jittered columns: 2 x 0.6 x h/4 = 0.3h short of the
    true width with independent draws (the expected minimum of four uniform draws), less
    with shared ones, so a cut width compared across the modes measured the sampling
    (paper scale: finest 9.9 mm, adaptive 11.6 mm; unjittered both 12.5-12.6 mm). The
    first layer's mean is within 2% of 2h for both: the median over 100 bins of four-draw
    means, whose standard error is about 0.6% of 2h."""
    h = 0.01
    left = _block((-0.195, 0, 0), (-0.005, 0.2, 0.2), h)  # last layer at x = -0.01
    right = _block((0.005, 0, 0), (0.195, 0.2, 0.2), h)   # first layer at x = +0.01
    x = np.concatenate([left, right])
    rng = np.random.default_rng(1)
    independent = x + rng.uniform(-h / 4, h / 4, x.shape)
    _, family = np.unique(np.floor(x / (3 * h) + 1e-9).astype(int), axis=0, return_inverse=True)
    shared = x + rng.uniform(-h / 4, h / 4, (family.max() + 1, 3))[family.reshape(-1)]
    widths = {}
    for name, pts in (("independent", independent), ("shared", shared)):
        g = cut_gap(pts, (0, 0, 0), (1, 0, 0), bin_size=2 * h, band=0.1, layer=h)
        assert g["bins"] == 100
        assert g["width"] == pytest.approx(2 * h, rel=0.02)
        widths[name] = cut_gap(pts, (0, 0, 0), (1, 0, 0), bin_size=2 * h, band=0.1)["width"]  # the nearest particle
    assert widths["independent"] < 0.9 * 2 * h  # the bias the first layer's mean removes
    assert widths["shared"] - widths["independent"] > 0.05 * 2 * h  # and it differs between the modes' jitters


def test_a_cut_is_measured_only_where_the_blade_has_been():
    """A blade a third of the way down a block: the lower part is whole, sampled at a
    finer spacing than the cut's gap. Over the whole plane the median "gap" would be that
    spacing; over what the blade swept it is the cut."""
    h = 0.01
    top = np.concatenate([_block((-0.2, 0.1, 0), (-0.05, 0.2, 0.1), h), _block((0.05, 0.1, 0), (0.2, 0.2, 0.1), h)])
    bottom = _block((-0.2, -0.1, 0), (0.2, 0.1, 0.1), h / 2)  # whole, 5 mm from face to face across the plane
    x = np.concatenate([top, bottom])
    blade = (np.array([0.0, 0.3, 0.05]), euler_matrix((0.0, 90.0, 0.0)), 0.2, 0.2)  # the plane x = 0, edge at y = 0.2
    assert not swept_by(x, blade, margin=0.0).any()
    blade = (np.array([0.0, 0.2, 0.05]), euler_matrix((0.0, 90.0, 0.0)), 0.2, 0.2)  # edge at y = 0.1
    swept = swept_by(x, blade, margin=0.02)
    assert swept.any() and (x[swept, 1] >= 0.12).all() and not (x[~swept, 1] >= 0.12).any()
    whole_plane = cut_gap(x, (0, 0, 0), (1, 0, 0), bin_size=0.02, band=0.1)["width"]
    assert whole_plane == pytest.approx(0.005)  # the whole part's spacing decides the median
    assert cut_gap(x[swept], (0, 0, 0), (1, 0, 0), bin_size=0.02, band=0.1)["width"] == pytest.approx(0.11)


def _scene(**kw):
    return Scene(
        name=kw.pop("name", "tiny_cmp"),
        simulation=SimulationSettings(domain_max=(0.4, 0.4, 0.4), dx=0.05, duration=0.2, **kw),
        materials=[Elastic(name="jelly", youngs_modulus=1.0e4)],
        bodies=[BoxBody(material="jelly", min=(0.1, 0.0, 0.1), max=(0.3, 0.15, 0.3))],
    )


def test_escaped_counts_non_finite_and_outside():
    x = np.array([[0.1, 0.1, 0.1], [np.nan, 0.1, 0.1], [0.5, 0.1, 0.1], [0.2, -0.03, 0.2], [0.2, -0.02, 0.2]])
    assert escaped(x, _scene()) == 3  # 2 cm below the floor is within half a cell (dx 5 cm)


def test_hourglass_outside_uses_the_glass_profile():
    s = load_scene("hourglass")  # neck (radius 0.015) at (0.2, 0.35, 0.2)
    x = np.array([[0.2, 0.35, 0.2], [0.2 + 0.05, 0.35, 0.2], [0.2 + 0.12, 0.2, 0.2], [0.39, 0.69, 0.39]])
    # inside at the neck; 5 cm off the axis at the neck is outside; inside the lower bulb;
    # above the mouth (outside the glass's height) is not counted
    assert hourglass_outside(s, x, margin=0.025) == 1


def test_panel_crossings_through_solid_panel_are_leaks():
    from abmpm.geometry.glyphs import letter_hole_polygons

    s = load_scene("letter_panel")  # panel 1.2 x 0.6 centred at (0.6, 0.3, 0.4), normal z
    hole = letter_hole_polygons("MPM", (1.2, 0.6))[0].representative_point()
    through_hole = (0.6 + hole.x, 0.3 + hole.y)
    solid = (0.6 - 0.55, 0.3 - 0.25)  # a corner of the panel, far from any letter
    x0 = np.array([[*through_hole, 0.35], [*solid, 0.35], [*solid, 0.30]])
    x1 = np.array([[*through_hole, 0.45], [*solid, 0.45], [*solid, 0.38]])  # the third stays in front

    def frame(x):
        return {"x": x, "id": np.arange(len(x)), "mass": np.ones(len(x))}

    assert panel_crossings_through_material(s, [(0.0, frame(x0)), (0.1, frame(x1))], margin=0.03) == 1


def test_panel_fast_pass_into_a_hole_is_not_a_leak():
    """Between two frames a fast particle slides from over the material into a letter
    and through it: the straight line between its frame positions meets the plane over
    material (farther than the margin from the rim), but a path through the hole only
    1.1 times as long explains it (paper_panel at 3 m/s moves 2-7 cm per frame). The
    same displacement next to no hole is a leak."""
    from abmpm.geometry.glyphs import letter_hole_polygons

    s = load_scene("letter_panel")
    m = 0.03
    hole = letter_hole_polygons("MPM", (1.2, 0.6))[1]  # the P, whose stem's left rim is straight
    rim = np.array([hole.bounds[0], 0.0])
    inward = np.array([1.0, 0.0])
    a = rim - 1.5 * m * inward  # over material, 1.5 margins from the rim (the M is farther)
    b = rim + 0.5 * m * inward  # over the hole
    centre = np.array([0.6, 0.3, 0.4])
    x0 = np.array([[*(centre[:2] + a), 0.399]])  # a hair in front of the sheet
    x1 = np.array([[*(centre[:2] + b), 0.42]])  # behind it, over the hole

    def frame(x):
        return {"x": x, "id": np.arange(len(x)), "mass": np.ones(len(x))}

    assert panel_crossings_through_material(s, [(0.0, frame(x0)), (0.1, frame(x1))], margin=m) == 0
    corner = np.array([0.05, 0.05])  # the same motion at the panel's corner, far from any letter
    y0, y1 = x0.copy(), x1.copy()
    y0[0, :2], y1[0, :2] = corner, corner + (b - a)
    assert panel_crossings_through_material(s, [(0.0, frame(y0)), (0.1, frame(y1))], margin=m) == 1


def test_hourglass_splash_over_the_rim_is_not_a_leak():
    from abmpm.compare.outcomes import leaks

    s = load_scene("hourglass")  # the glass spans y 0.05 to 0.65; bulbs of radius 0.15 about (0.2, 0.2)
    inside = [0.2, 0.2, 0.2]
    f0 = {"x": np.array([[0.2, 0.7, 0.2], [0.2, 0.5, 0.2], inside]), "id": np.array([0, 1, 2])}
    f1 = {"x": np.array([[0.39, 0.5, 0.2], [0.2, 0.5, 0.39], inside]), "id": np.array([0, 1, 2])}  # 0 and 1 outside
    for f in (f0, f1):
        f["mass"] = np.ones(3)
    out = leaks(s, [(0.0, f0), (0.1, f1)])
    assert out["outside_glass"] == 1 and out["over_the_mouth"] == 1 and out["total"] == 1


# --------------------------------------------------------------------------- a comparison


def test_compare_tiny_scene_writes_table_and_report(tmp_path):
    out = tmp_path / "cmp"
    recs = compare(_scene(), modes=("original", "finest"), out=out, frames=2, device="cpu")
    assert [r["mode"] for r in recs] == ["original", "finest"]
    table = json.loads((out / "table1.json").read_text())["records"]
    assert len(table) == 2
    for r in table:
        for key in ("scene", "mode", "particles_mean", "particles_end", "steps_per_second",
                    "wall_seconds_per_sim_second", "outcome", "leaks", "status"):
            assert key in r, key
        assert r["status"] == "completed"
        assert r["leaks"]["total"] == 0
        assert "mass_below_mid_height" in r["outcome"]["final"]
        summary = json.loads((out / "tiny_cmp" / r["mode"] / "summary.json").read_text())
        steps, clock = summary["series"]["steps"], summary["series"]["sim_seconds"]
        assert steps[0] == 0 and steps[-1] == summary["steps"] and np.all(np.diff(steps) > 0)
        assert clock[0] == 0.0 and np.all(np.diff(clock) > 0) and clock[-1] <= summary["sim_seconds"] + 1e-3
    orig, fine = table
    assert fine["particles_end"] == 8 * orig["particles_end"]  # b = 2: 8 times the particles
    report = (out / "report.md").read_text()
    links = re.findall(r"\]\(([^)]+\.png)\)", report)
    assert links and all((out / link).is_file() for link in links)
    assert "tiny_cmp" in report and "finest" in report
    # a second comparison of another mode adds to the table
    compare(_scene(), modes=("adaptive",), out=out, frames=1, device="cpu")
    modes = [r["mode"] for r in json.loads((out / "table1.json").read_text())["records"]]
    assert sorted(modes) == ["adaptive", "finest", "original"]
    # measured again from the run folders alone: the same figures
    again = remeasure(out)
    assert [r["particles_end"] for r in again] == [r["particles_end"] for r in
                                                    json.loads((out / "table1.json").read_text())["records"]]


# --------------------------------------------------------------------------- paper scenes


@pytest.mark.parametrize("name", PAPER_SCENES)
def test_paper_scene_and_its_quick_version_validate(name):
    s = load_scene(name)
    assert s.name == name and name in PAPER_TABLE1
    q = quick_scene(s)
    assert q.simulation.dx > s.simulation.dx
    assert q.simulation.duration <= s.simulation.duration
    for mode in MODES:
        with_mode(q, mode).check_feasible(mode, "cpu")
    assert set(QUICK_OVERRIDES) == set(PAPER_SCENES)


@pytest.mark.parametrize("name", PAPER_SCENES)
def test_paper_scene_quick_version_steps(name):
    from abmpm.scene.loader import list_builtin_scenes
    from abmpm.simulation import Simulation

    assert list_builtin_scenes()[name].startswith("Paper Fig.")
    sim = Simulation(quick_scene(load_scene(name)), device="cpu")  # adaptive, as the scene says
    for _ in range(2):
        sim.step()
    p = sim.particles()
    assert np.isfinite(p.x).all() and np.isfinite(p.v).all()


def test_window_figures_time_only_the_frames_after_contact():
    series = {"time": [0.0, 0.1, 0.2, 0.3], "steps": [0, 10, 30, 60], "sim_seconds": [0.0, 1.0, 2.0, 5.0],
              "count_per_level": [[10, 0], [8, 16], [6, 32], [4, 48]]}
    w = window_figures(series, 1)
    # frames 1..3: 50 steps in 4 s of simulation for 0.2 s of simulated time
    assert w["steps"] == 50 and w["steps_per_second"] == 12.5
    assert w["wall_seconds_per_sim_second"] == pytest.approx(20.0)
    assert w["start"] == 0.1 and w["end"] == 0.3
    assert w["particles_mean"] == pytest.approx((38 + 52) / 2) and w["particles_end"] == 52
    assert window_figures(series, 3) is None  # nothing after the last frame
    assert window_figures({**series, "sim_seconds": [None, None, 2.0, 5.0]}, 1) is None  # frames of an earlier run


def test_window_frames_follow_the_contact_time():
    fps = 30.0
    for name, t in PAPER_CONTACT.items():
        first, frames = window_frames(t, 0.2, fps)
        assert (first - 1) / fps < t <= first / fps  # the first output frame at or after contact
        assert frames - first == 6


@pytest.mark.parametrize("name, axis, toward, barrier, speed", [
    ("paper_panel", 2, +1, 0.305, 3.0),  # the panel's plane z, the bunny's speed along z
    ("paper_bunny_split", 1, -1, 0.16 + 0.15, 1.0),  # the blades' top edge, falling at 1 m/s plus gravity
])
def test_paper_contact_times_match_the_scene_geometry(name, axis, toward, barrier, speed):
    """PAPER_CONTACT against the sampled body: the first particle reaches the collider
    then (to 2 ms, a tenth of the window's frame; the bodies' sampling moves their
    extreme point by less than half a particle spacing, 0.6 ms at these speeds)."""
    from abmpm.simulation import Simulation

    sc = load_scene(name)
    assert sc.colliders[0].center[axis] == pytest.approx(0.305 if axis == 2 else 0.16)
    x = Simulation(with_mode(sc, "original"), device="cpu").particles().x[:, axis]
    gap = barrier - x.max() if toward > 0 else x.min() - barrier
    g = 0.0 if axis == 2 else 9.81
    t = gap / speed if g == 0.0 else (-speed + np.sqrt(speed**2 + 2 * g * gap)) / g
    assert PAPER_CONTACT[name] == pytest.approx(t, abs=2e-3)


def test_adaptive_against_finest_figures():
    from abmpm.compare.report import adaptive_against_finest, paper_against_finest

    a = {"steps_per_second": 40.0, "particles_mean": 10_000, "wall_seconds_per_sim_second": 30.0}
    f = {"steps_per_second": 20.0, "particles_mean": 40_000, "wall_seconds_per_sim_second": 60.0}
    got = adaptive_against_finest(a, f)
    # twice the steps/s with a quarter of the particles: an adaptive particle-step costs twice a finest one
    assert got["score"] == pytest.approx(0.5) and got["wall"] == pytest.approx(0.5)
    assert adaptive_against_finest({**a, "steps_per_second": None}, f)["score"] is None
    # Table 1 of the paper (GTX 1650): panel 2.7 / 2.4 steps/s with 71k / 141k particles,
    # hourglass 3.0 / 1.7 with 167k / 304k
    assert paper_against_finest("paper_panel")["score"] == pytest.approx(2.7 / 2.4 * 71 / 141)
    assert paper_against_finest("paper_hourglass")["wall"] == pytest.approx(1.7 / 3.0)


def test_apply_overrides_sets_list_items():
    s = apply_overrides(load_scene("paper_panel"), {"colliders.0.text": "AB", "simulation.dx": 0.02})
    assert s.colliders[0].text == "AB" and s.simulation.dx == 0.02


# --------------------------------------------------------------------------- CLI


@pytest.mark.parametrize("argv, word", [
    (["compare", "tiny_no_such_scene"], "unknown scene"),
    (["compare", "paper_cut", "--modes", "coarse"], "unknown mode"),
    (["paper", "--scenes", "paper_nope"], "unknown paper scene"),
    (["compare", "paper_cut", "--set", "simulation.dx=0.1,0.2"], "one value here"),
    (["paper", "--scenes", "paper_cut", "--window", "0"], "--window"),
    (["paper", "--scenes", "paper_cut", "--window", "nan"], "--window"),
    (["paper", "--scenes", "paper_cut", "--window", "0.1", "--frames", "2"], "--window and --frames"),
    (["paper", "--scenes", "paper_cut", "--set", "simulation.no_such_key=1"], "no_such_key"),
    (["paper", "--remeasure"], "no runs to measure again"),
])
def test_cli_errors(argv, word, capsys, tmp_path):
    assert main(argv + ["--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and word in err[0]
    assert not (tmp_path / "x").exists()


def test_cli_set_changes_every_run(tmp_path):
    """abmpm compare/paper --set KEY=VALUE: the setting reaches the runs' scenes."""
    out = tmp_path / "cmp"
    assert main(["compare", "dam_break", "--modes", "original", "--frames", "1", "--quiet",
                 "--set", "simulation.refinement.merge=true", "--set", "simulation.fps=50", "--out", str(out)]) == 0
    scene = json.loads((out / "dam_break" / "original" / "scene.json").read_text())
    assert scene["simulation"]["fps"] == 50 and scene["simulation"]["refinement"]["merge"] is True
    # --remeasure runs nothing: the table is measured again from the run's own folder
    table = out / "table1.json"
    record = json.loads(table.read_text())["records"][0]
    table.write_text(json.dumps({"records": [{**record, "outcome": {}}]}))
    assert main(["compare", "dam_break", "--remeasure", "--quiet", "--out", str(out)]) == 0
    again = json.loads(table.read_text())["records"]
    assert len(again) == 1 and again[0]["outcome"] == record["outcome"] and again[0]["steps"] == record["steps"]
