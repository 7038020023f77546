"""A time step per level (sim/time_levels.py, docs/method.md "A time step per level"):
the level-0 particles far from the fine level (the slow set) take the coarse step while
the rest take k fine substeps. Tolerances are stated inline."""

import numpy as np
import pytest
import warp as wp

import abmpm
from abmpm.bench.interface import TANK_DEPTH, tank_at_rest
from abmpm.scene import model as sm
from abmpm.sim.refine import BESIDE_CELLS
from abmpm.sim.time_levels import GUARD_HALO, SLOW_STEP_COST, SORT_HALO, cut_for_levels
from abmpm.simulation import Simulation

STIFF = 4.0e5  # Pa: stiff enough that the fine CFL step (not max_dt) sets dt, so k = 2 at b = 2


def per_level(scene: abmpm.Scene, time_steps: str = "per_level") -> abmpm.Scene:
    r = scene.simulation.refinement.model_copy(update={"time_steps": time_steps})
    return scene.model_copy(update={"simulation": scene.simulation.model_copy(update={"refinement": r})})


def flight(time_steps: str) -> abmpm.Scene:
    """A jelly bar flying (no gravity, walls far away) towards a jelly block at rest in a
    refinement box: its front crosses from the slow set into the fast halo around the
    box, and stops two coarse cells short of the box (the level interface is not crossed)."""
    return abmpm.Scene(
        simulation=abmpm.SimulationSettings(
            domain_max=(2.0, 1.0, 1.0), dx=0.05, fps=40, gravity=(0, 0, 0),
            refinement={"mode": "adaptive", "factor": 2, "boxes": [((1.5, 0.3, 0.3), (1.7, 0.7, 0.7))],
                        "time_steps": time_steps}),
        materials=[abmpm.Elastic(name="jelly", youngs_modulus=STIFF)],
        bodies=[abmpm.BoxBody(material="jelly", min=(0.45, 0.35, 0.35), max=(1.25, 0.65, 0.65), velocity=(1.0, 0, 0)),
                abmpm.BoxBody(material="jelly", min=(1.55, 0.4, 0.4), max=(1.65, 0.6, 0.6))])


def momentum(p) -> np.ndarray:
    return (p.mass[:, None].astype(np.float64) * p.v).sum(axis=0)


def test_the_frame_cut_is_the_cheapest_that_keeps_both_cfl_steps():
    # a frame of 0.05 s, the fast set's CFL step 0.565 ms, the slow set's 1 ms (max_dt
    # binds it: 1.77 substeps, so the fewest substeps give it k = 1)
    rest, dt_max, slow_dt = 0.05, 0.565e-3, 1.0e-3
    fewest = 89  # ceil(0.05 / 0.565e-3)
    assert cut_for_levels(rest, dt_max, slow_dt, 4, 0, 1000.0, 100) == (fewest, 1)  # nothing slow: as before
    # many slow particles beside a small fast part: 100 substeps of 0.5 ms, S steps 1 ms
    # (cost a frame: 100 (1000 + 1.4 / 2 1e5 + node work) against 89 (1000 + 1e5))
    assert cut_for_levels(rest, dt_max, slow_dt, 4, 100_000, 1000.0, 100) == (100, 2)
    # a fast part that costs more than S saves: the fewest substeps
    assert cut_for_levels(rest, dt_max, slow_dt, 4, 100_000, 2.0e6, 100) == (fewest, 1)
    # any cut: no substep longer than dt_max, no step of S longer than its CFL step (at k = 1
    # S steps with the fast set, whose signal then holds S's speed), and never more costly than the fewest substeps with k = 1 (what the global step costs)
    rng = np.random.default_rng(0)
    for _ in range(500):
        dt_max, ratio = rng.uniform(1e-4, 1e-2), rng.uniform(0.5, 6.0)
        n_slow, fast, nodes = int(rng.integers(0, 10**5)), rng.uniform(0, 1e5), int(rng.integers(1, 10**5))
        n, k = cut_for_levels(rest, dt_max, ratio * dt_max, 4, n_slow, fast, nodes)
        assert rest / n <= dt_max * (1 + 1e-9) and 1 <= k <= min(4, n)
        assert k == 1 or k * rest / n <= ratio * dt_max * (1 + 1e-9)
        global_cost = max(1, np.ceil(rest / dt_max - 1e-9)) * (fast + n_slow)
        slow = min(n_slow, n_slow * SLOW_STEP_COST / k + nodes * (0.032 / k + 0.008)) if k > 1 else n_slow
        assert n * (fast + slow) <= global_cost * (1 + 1e-9)


def test_free_flight_across_the_temporal_interface_conserves_momentum():
    sim = Simulation(flight("per_level"), device="cpu")
    p0 = sim.particles()
    P0, M0 = momentum(p0), p0.mass.astype(np.float64).sum()
    slow0 = sim.solver.slow_count
    sim.advance(frames=5)
    p = sim.particles()
    # the slow set took the coarse step (k = 2 substeps each) and lost particles to the halo
    assert sim.solver.block == 2 and 0 < sim.solver.slow_count < slow0
    # float32 momentum round-off: ~6e-8 relative per substep, ~300 substeps; the global
    # step's run of the same scene drifts 1.7e-6 (measured), a 1e-5 bound leaves room for
    # the accumulation and fails where a node's slow share is dropped or counted twice
    assert np.abs(momentum(p) - P0).max() < 1e-5 * np.abs(P0).max()
    assert p.mass.astype(np.float64).sum() == M0  # no split, no merge: every mass as it was
    # the same flight with one global step: the bar's centre within 1e-4 of its 0.125 m path
    ref = Simulation(flight("global"), device="cpu")
    ref.advance(frames=5)
    q = ref.particles()
    bar_p, bar_q = p.x[:, 0] < 1.45, q.x[:, 0] < 1.45
    assert abs(p.x[bar_p, 0].mean() - q.x[bar_q, 0].mean()) < 1e-4


def test_tank_at_rest_across_the_temporal_interface_stays_at_rest():
    # The right half refined, the left far from it slow: the water starts at its
    # hydrostatic J (Tait, gamma 7). Nothing may move faster than with one global step:
    # 1.25x its fastest particle (measured 1.0x overall, 1.12x in the slow left quarter),
    # and J in the slow part within 0.002 of hydrostatic (1st-99th percentile; global
    # step measured -0.0017..+0.0014, per level -0.0019..+0.0016).
    fastest = {}
    for time_steps in ("per_level", "global"):
        scene = per_level(tank_at_rest("adaptive", 0.05, 2), time_steps)
        water = scene.materials[0].model_copy(update={"bulk_modulus": STIFF})
        sim = Simulation(scene.model_copy(update={"materials": [water]}), device="cpu")
        y = sim.particles().by_id().x[:, 1]
        sim.set_particles(history=hydrostatic(y).astype(np.float32))
        sim.advance(seconds=0.2)
        p = sim.particles()
        if time_steps == "per_level":
            assert sim.solver.block == 2 and sim.solver.slow_count > 0
            left = (p.x[:, 0] < 0.25) & (p.x[:, 1] > 0.1) & (p.x[:, 1] < TANK_DEPTH - 0.1)
            assert np.abs(np.percentile(p.J[left] - hydrostatic(p.x[left, 1]), [1, 99])).max() < 0.002
        fastest[time_steps] = np.linalg.norm(p.v, axis=1).max()
    assert fastest["per_level"] < 1.25 * fastest["global"], fastest


def hydrostatic(y: np.ndarray) -> np.ndarray:
    return (1.0 + 7.0 * 1000.0 * 9.81 * np.clip(TANK_DEPTH - y, 0.0, None) / STIFF) ** (-1.0 / 7.0)


def test_per_level_resume_is_bit_identical():
    scene = flight("per_level")
    straight = Simulation(scene, device="cpu")
    straight.advance(frames=4)
    first = Simulation(scene, device="cpu")
    first.advance(frames=2)
    arrays, meta = first.state_dict()
    resumed = Simulation(scene, device="cpu")
    resumed.load_state_dict(arrays, meta)
    resumed.advance(frames=2)
    a, b = straight.particles().by_id(), resumed.particles().by_id()
    assert straight.steps == resumed.steps and straight.solver.slow_count > 0
    assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v)


def test_sloshing_into_the_refined_box_with_the_slow_set_open():
    # Water flows into the refinement box and splits while the slow set's step is open
    # (the refinement sorts only the fast part then). Against the global step: mass
    # exact (b = 2 children carry m/8, exact in float32), the water's centre of mass
    # within 1 mm of the global run's (it moves 50 mm in the window; measured 0.54 mm
    # apart: the slow set's longer step is the only difference), the fastest particle
    # within 10% (measured 0.3%).
    from abmpm.bench.scaling import sloshing_tank

    runs = {}
    for mode in ("per_level", "adaptive"):
        scene = sloshing_tank(2, mode)
        water = scene.materials[0].model_copy(update={"bulk_modulus": STIFF})
        sim = Simulation(scene.model_copy(update={"materials": [water]}), device="cpu")
        m0 = sim.particles().mass.astype(np.float64).sum()
        refiner, splits_open = sim.solver.refiner, []
        split = refiner.split

        def counted(*args, **kwargs):
            n = split(*args, **kwargs)
            splits_open.append(n if sim.solver.slow.open else 0)
            return n

        if mode == "per_level":
            refiner.split = counted
        sim.advance(seconds=0.15)
        p = sim.particles()
        assert p.mass.astype(np.float64).sum() == m0
        runs[mode] = (float((p.mass * p.x[:, 0]).sum() / p.mass.sum()), float(np.linalg.norm(p.v, axis=1).max()))
        if mode == "per_level":
            assert sim.solver.block == 2 and sim.solver.slow_count > 0 and sum(splits_open) > 0
    (xa, va), (xb, vb) = runs["per_level"], runs["adaptive"]
    assert abs(xa - xb) < 1e-3 and abs(va / vb - 1) < 0.1, runs


def test_segments_and_captured_graphs_give_the_slow_set_one_substep_at_a_time():
    # Segments of up to SEGMENT_MAX substeps end with the slow set's step; a captured
    # graph holds the grid update's slow-set arguments. One substep at a time, eager
    # segments and (where Warp replays CPU graphs) captured ones: bit-identical.
    from abmpm.sim.solver import SEGMENT_MAX

    def run(max_segment, capture):
        sim = Simulation(flight("per_level"), device="cpu")
        sim.max_segment, sim.solver.capture = max_segment, capture
        sim.advance(frames=2)
        p = sim.particles().by_id()
        assert sim.solver.block == 2 and sim.solver.slow_count > 0
        assert not capture or len(sim.solver._graphs) > 0
        return sim.steps, p.x, p.v

    one = run(1, False)
    runs = [run(SEGMENT_MAX, False)]
    try:
        with wp.ScopedCapture(device="cpu", force_module_load=False) as capture:
            pass
        wp.capture_launch(capture.graph)
        runs.append(run(SEGMENT_MAX, True))
    except RuntimeError as err:  # a Warp that replays no graph on the CPU (before 1.19)
        assert "cuda" in str(err).lower() or "capture" in str(err).lower()
    for other in runs:
        assert other[0] == one[0] and np.array_equal(other[1], one[1]) and np.array_equal(other[2], one[2])


def test_one_and_two_threads_agree_and_a_nan_in_the_slow_set_stops_the_run(monkeypatch, poison_velocity):
    # Two threads scatter the slow set into private sums added in part order: the same
    # threads give the same particles bit for bit, one thread the same up to float32
    # summation order (1e-6 m after 2 frames, far below the 1 m/s flight's 0.05 m).
    from abmpm.errors import SimulationBlowUp

    runs = {}
    for threads in (2, 2, 1):
        monkeypatch.setenv("ABMPM_THREADS", str(threads))
        sim = Simulation(flight("per_level"), device="cpu")
        sim.advance(frames=2)
        assert sim.solver.block == 2 and sim.solver.slow_count > 0
        p = sim.particles().by_id()
        if threads in runs:
            assert np.array_equal(runs[threads].x, p.x) and np.array_equal(runs[threads].v, p.v)
        runs[threads] = p
    assert np.abs(runs[1].x - runs[2].x).max() < 1e-6
    # a non-finite velocity in the slow set is caught at its step's end, like any other
    p = sim.particles().by_id()
    rear = np.argmin(p.x[:, 0])  # the bar's rear
    poison_velocity(sim, [p.id[rear]])
    stored = sim.particles()  # storage order: the slow set first
    assert np.flatnonzero(stored.id == p.id[rear])[0] < sim.solver.slow_count
    with pytest.raises(SimulationBlowUp, match="NaN"):
        sim.advance(frames=1)


# --------------------------------------------------------------------------- GPU


@pytest.mark.cuda
def test_the_slow_set_on_cuda_agrees_with_the_cpu_and_its_graphs(cuda_available):
    # The per-level step on the GPU: the same flight on CPU, on CUDA eager and on CUDA with
    # captured graphs. GPU atomics add in another order, so positions agree to float32
    # round-off (1e-7 relative per add over ~100 substeps of a 1 m/s flight: ~1e-5 m;
    # 1e-4 m = dx/500 bounds it and is far below a substep's motion, 1.2e-3 m, which a
    # slow set stepped with the wrong dt or a stale graph argument would show).
    if not cuda_available:
        pytest.skip("no CUDA device on this machine")
    runs = {}
    for device, capture in (("cpu", False), ("cuda", False), ("cuda", True)):
        scene = flight("per_level")
        scene = scene.model_copy(update={"simulation": scene.simulation.model_copy(update={"cuda_graph": capture})})
        sim = Simulation(scene, device=device)
        p0 = sim.particles()
        P0 = momentum(p0)
        sim.advance(frames=3)
        assert sim.solver.block == 2 and sim.solver.slow_count > 0
        assert not capture or sim.solver._graphs
        p = sim.particles()
        # the same 1e-5 momentum bound as on the CPU (test above)
        assert np.abs(momentum(p) - P0).max() < 1e-5 * np.abs(P0).max()
        runs[(device, capture)] = (sim.steps, p.by_id())
    (s0, a) = runs[("cpu", False)]
    for key in (("cuda", False), ("cuda", True)):
        s, b = runs[key]
        assert s == s0 and len(a) == len(b)
        assert np.abs(a.x - b.x).max() < 1e-4
        assert np.abs(a.v - b.v).max() < 1e-2 * max(1.0, np.abs(a.v).max())


@pytest.mark.parametrize("flip", [False, True], ids=["front-face", "back-face"])
def test_the_slow_set_lands_on_a_sheet_as_the_global_step_does(flip):
    # Stiff water falls on to a sheet far from a refinement box (the sheet's coarse contact
    # band holds it about a coarse cell above): it lands in the slow set (k = 2), whose
    # particles near the sheet scatter to their side's nodes only (CPIC at the step's
    # open) and cast their whole step's path at its close. Against the global step of the
    # same scene: no particle ever below the sheet (the guarantee), mass exact, and the
    # water's mean height at 0.2 s within 2 mm of the global run's (a tenth of a fine
    # cell: both land on the same sheet with the same coarse contact; measured 0.8 mm
    # apart on the CPU, 1.1 mm on CUDA, and 20 mm with the slow set's scatter blind to
    # the sheet). The sheet's winding plays no part: the water lands on either face.
    sheet_y, edge = 0.2, 0.68
    heights = {}
    for time_steps in ("per_level", "global"):
        scene = abmpm.Scene(
            simulation=abmpm.SimulationSettings(
                domain_max=(1.2, 0.6, 0.2), dx=0.04, fps=50,
                refinement={"mode": "adaptive", "factor": 2, "boxes": [((1.0, 0.0, 0.0), (1.2, 0.6, 0.2))],
                            "time_steps": time_steps}),
            materials=[abmpm.Fluid(name="water", bulk_modulus=STIFF)],
            bodies=[abmpm.BoxBody(material="water", min=(0.1, 0.24, 0.0), max=(0.5, 0.4, 0.2))],
            colliders=[sm.SheetCollider(size=(0.7, 0.3), center=(0.35, sheet_y, 0.1),
                                        rotation=(180.0 if flip else 0.0, 0.0, 0.0))])
        sim = Simulation(scene, device="cpu")
        m0 = sim.particles().mass.astype(np.float64).sum()
        colored_slow = 0
        while sim.time < 0.2 - 1e-9:
            sim.advance(frames=1)
            p = sim.particles()
            over = p.x[:, 0] < edge
            assert (p.x[over, 1] > sheet_y).all(), time_steps
            if time_steps == "per_level":
                n = sim.solver.slow_count
                colored_slow = max(colored_slow, int((sim._state.surface_body.numpy()[:n] >= 0).sum()))
        assert p.mass.astype(np.float64).sum() == m0
        if time_steps == "per_level":
            assert sim.solver.block == 2 and colored_slow > 0, (sim.solver.block, colored_slow)
        heights[time_steps] = float((p.mass * p.x[:, 1]).sum() / p.mass.sum())
    assert abs(heights["per_level"] - heights["global"]) < 2e-3, heights


def test_the_slow_set_shares_no_coarse_node_with_a_child():
    # The slow set stays GUARD_HALO coarse cells from the core, and two coarse stencils
    # (x +- 1.5 dx) share no node more than three cells apart: no node holding S's mass is
    # reached by a level-1 particle's overlap scatter (Eq. 8), which reaches only nodes
    # marked in the same substep (S, frozen for its step, marks none). The halos say so (a
    # smaller guard fails here: with 1 cell it also took the paper panel off its path,
    # docs/method.md); the flight's open steps confirm it node by node.
    assert GUARD_HALO >= 3 and GUARD_HALO >= BESIDE_CELLS and SORT_HALO - GUARD_HALO >= 2
    sim = Simulation(flight("per_level"), device="cpu")
    g = sim.solver.grid
    checked = 0
    for _ in range(120):
        sim.step()
        slow = sim.solver.slow
        if not slow.open:
            continue
        held = np.flatnonzero(slow.nodes.m.numpy()[:g.node_count] > 0.0)
        p = sim.particles()
        base = np.floor((p.x[p.level == 1] - g.origin) / g.dx - 0.5).astype(int)
        reached = set()
        for o in np.ndindex(3, 3, 3):
            c = base + np.array(o)
            reached.update(np.ravel_multi_index(c.T, g.dims).tolist())
        assert held.size and not reached.intersection(held.tolist())
        checked += 1
    assert checked > 20  # the bar's slow part stepped at k = 2 throughout
