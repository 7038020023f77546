"""A step ready for CUDA graphs (docs/architecture.md, "Segments and CUDA graphs").

On the CPU, for real: a substep allocates nothing and reads nothing back (Warp's
allocation and read-back entry points are recorded while it runs, and the recorder
is shown to catch both); segments of several substeps, run eagerly or as graphs
that Warp replays on the CPU, give bit-identical particles to one substep at a
time, also when a re-cut of the time step or a blow-up rewinds a segment. On a GPU
(skipped without one): captured and eager segments agree.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
import warp as wp

import abmpm
from abmpm.errors import SimulationBlowUp
from abmpm.scene import model as sm
from abmpm.sim import parallel
from abmpm.sim.solver import SEGMENT_MAX, MPMSolver
from abmpm.simulation import init_warp

# --------------------------------------------------------------------------- scenes


def sheet_scene(mode: str, **motion) -> abmpm.Scene:
    """Water falling onto a tilted static sheet (a thin collider: CPIC transfers). The
    paper's density criterion refines the whole sheet, so that particles split and
    merge at the host points (the feature criterion would leave a free sheet coarse)."""
    sheet = sm.SheetCollider(size=(0.6, 0.6), center=(0.5, 0.2, 0.5), rotation=(10.0, 0.0, 5.0), motion=motion)
    refinement = {"mode": mode, "merge": True, "criterion": "density"}
    return abmpm.Scene(
        simulation=abmpm.SimulationSettings(dx=0.05, fps=30, refinement=refinement),
        materials=[abmpm.Fluid(name="water")],
        bodies=[abmpm.BoxBody(material="water", min=(0.35, 0.3, 0.35), max=(0.65, 0.5, 0.65),
                              velocity=(0.0, -1.0, 0.0))],
        colliders=[sheet],
    )


def impact_scene() -> abmpm.Scene:
    """Water at 20 m/s onto a turned-over sheet (test_cfl.py): the rest of a frame is
    re-cut many times, in the middle of segments."""
    text = (Path(__file__).parent / "test_cfl.py").read_text().split('IMPACT = """')[1].split('"""')[0]
    return sm.Scene.model_validate(tomllib.loads(text.format(speed=20.0, separation=0.0, duration=0.1, stiffening="particle")))


@pytest.fixture
def two_parts(monkeypatch):
    """Two CPU threads with small ranges: the private P2G grids and their gather run."""
    monkeypatch.setenv("ABMPM_THREADS", "2")
    monkeypatch.setattr(parallel, "MIN_RANGE", 256)


def cpu_graphs() -> bool:
    """Whether this Warp replays graphs on the CPU (1.19 and later)."""
    init_warp()
    try:
        with wp.ScopedCapture(device="cpu", force_module_load=False) as capture:
            pass
        wp.capture_launch(capture.graph)
        return True
    except Exception:  # older Warp: "Must be a CUDA device" or similar
        return False


# --------------------------------------------------------------------------- recorder


ALLOCATE = ("empty", "zeros", "zeros_like", "empty_like", "clone", "full", "full_like", "ones", "ones_like")
SYNC = ("synchronize", "synchronize_device", "synchronize_stream")
READ = ("numpy", "list", "__getitem__", "assign")  # device -> host reads, host -> device writes


class Recorder:
    """Records Warp allocations, host reads and synchronisations while ``armed``."""

    def __init__(self, monkeypatch):
        self.armed = False
        self.calls: list[str] = []
        for name in ALLOCATE + SYNC:
            if hasattr(wp, name):
                monkeypatch.setattr(wp, name, self._wrap(getattr(wp, name), f"wp.{name}"))
        for name in READ + ("__init__",):  # __init__: any array object, allocated or a view
            monkeypatch.setattr(wp.array, name, self._wrap(getattr(wp.array, name), f"wp.array.{name}"))
        copy = wp.copy

        def copy_between_devices(dest, src, *args, **kwargs):
            if self.armed and dest.device != src.device:
                self.calls.append("wp.copy between devices")
            return copy(dest, src, *args, **kwargs)

        monkeypatch.setattr(wp, "copy", copy_between_devices)
        monkeypatch.setattr(wp.Mesh, "refit", self._wrap(wp.Mesh.refit, "wp.Mesh.refit"))

    def _wrap(self, fn, name):
        def recorded(*args, **kwargs):
            if self.armed:
                self.calls.append(name)
            return fn(*args, **kwargs)

        return recorded

    def arm_in(self, solver: MPMSolver, method: str, monkeypatch) -> list[str]:
        """Record while ``solver.<method>`` runs; returns the list the calls go to
        (its first entry counts the runs)."""
        calls: list = [0]
        inner = getattr(solver, method)

        def armed(*args, **kwargs):
            calls[0] += 1
            outer, self.armed, self.calls = (self.armed, self.calls), True, calls
            try:
                return inner(*args, **kwargs)
            finally:
                self.armed, self.calls = outer

        monkeypatch.setattr(solver, method, armed)
        return calls


def recorded_run(monkeypatch, scene, mode, segments=3, capture=False):
    """Warm up for one segment (eagerly: buffers, kernels), then record ``segments``
    more of them: the calls made inside substeps (while a graph is captured, with
    ``capture``) and inside begin_segment. Returns the lists of calls, each after
    the number of runs it recorded."""
    sim = abmpm.Simulation(scene, device="cpu", mode=mode)
    sim.max_segment = SEGMENT_MAX
    sim.advance(seconds=SEGMENT_MAX * sim.dt)
    sim.solver.capture = capture
    recorder = Recorder(monkeypatch)
    in_substep = recorder.arm_in(sim.solver, "substep", monkeypatch)
    in_begin = recorder.arm_in(sim.solver, "begin_segment", monkeypatch)
    steps = sim.steps
    for _ in range(segments):
        sim._run_segment(sim.max_segment)
    assert sim.steps > steps + segments  # segments of several substeps ran
    assert in_substep[0] >= (1 if capture else sim.steps - steps) and in_begin[0] == segments
    return sim, in_substep[1:], in_begin[1:]


# --------------------------------------------------------------------------- no host work in a substep


def test_the_recorder_catches_allocations_and_read_backs(monkeypatch, two_parts):
    """The check below can fail: a substep with the old per-substep read-back of the
    CFL signal, or with an allocation, is caught."""
    init_warp()
    recorder = Recorder(monkeypatch)
    recorder.armed = True
    a = wp.zeros(4, dtype=float, device="cpu")
    wp.empty_like(a).numpy()
    wp.synchronize_device("cpu")
    recorder.armed = False
    seen = len(recorder.calls)
    wp.zeros(1, dtype=float, device="cpu")  # not armed: not recorded
    assert len(recorder.calls) == seen
    assert {"wp.zeros", "wp.array.__init__", "wp.empty_like", "wp.array.numpy", "wp.synchronize_device"} <= set(
        recorder.calls)

    sim = abmpm.Simulation(sheet_scene("original"), device="cpu")
    sim.max_segment = SEGMENT_MAX
    solver = sim.solver
    real = solver.substep

    def old_substep(state):  # the substep as it was: the signal read back every time
        real(state)
        solver.signal.numpy()

    monkeypatch.setattr(solver, "substep", old_substep)
    calls = recorder.arm_in(solver, "substep", monkeypatch)
    sim._run_segment(SEGMENT_MAX)
    assert calls[0] == SEGMENT_MAX and calls.count("wp.array.numpy") == SEGMENT_MAX

    def allocating_substep(state):
        real(state)
        solver._tau = wp.empty(state.capacity, dtype=wp.mat33, device=solver.device)

    monkeypatch.setattr(solver, "substep", allocating_substep)
    calls = recorder.arm_in(solver, "substep", monkeypatch)
    sim._run_segment(SEGMENT_MAX)
    assert "wp.empty" in calls


@pytest.mark.parametrize("mode", ["original", "adaptive", "finest"])
def test_a_substep_neither_allocates_nor_reads_back(monkeypatch, two_parts, mode):
    sim, in_substep, in_begin = recorded_run(monkeypatch, sheet_scene(mode), mode)
    assert in_substep == []
    if mode == "adaptive":
        assert sim.particle_count > 1200  # particles were split: refinement ran at host points
        assert "wp.array.numpy" in in_begin  # the split count, read back in begin_segment


@pytest.mark.skipif(not cpu_graphs(), reason="this Warp cannot replay graphs on the CPU")
@pytest.mark.parametrize("mode", ["original", "adaptive"])
def test_a_captured_substep_neither_allocates_nor_reads_back(monkeypatch, two_parts, mode):
    sim, in_substep, _ = recorded_run(monkeypatch, sheet_scene(mode), mode, capture=True)
    assert in_substep == []  # what the graphs hold: launches only
    assert sim.solver._graphs


def test_segments_are_announced_and_bounded():
    sim = abmpm.Simulation(sheet_scene("adaptive"), device="cpu")
    solver = sim.solver
    assert sim.max_segment == 1  # without captured graphs every substep is checked
    assert solver.segment_length == SEGMENT_MAX  # up to the next refinement step
    solver.begin_segment(sim._state, sim.time, sim.dt, 3)
    solver.run_segment(sim._state)
    assert solver.segment_length == 1 and solver.end_segment().shape == (3, 2)
    with pytest.raises(ValueError, match="1 to 1 substeps"):
        solver.begin_segment(sim._state, sim.time, sim.dt, 2)
    moving = abmpm.Simulation(sheet_scene("original", velocity=(0.0, 0.1, 0.0)), device="cpu")
    assert moving.solver.segment_length == 1  # the pose is uploaded before every substep


# --------------------------------------------------------------------------- same results


def run_particles(scene, mode, frames, max_segment=1, capture=False, by_step=False):
    sim = abmpm.Simulation(scene, device="cpu", mode=mode)
    sim.max_segment = max_segment
    sim.solver.capture = capture
    rewinds = []
    rewind = sim.solver.rewind
    sim.solver.rewind = lambda state, n: (rewinds.append(n), rewind(state, n))
    if by_step:  # the public one-substep API
        while sim.frame < frames:
            sim.step()
    else:
        sim.advance(frames=frames)
    p = sim.particles().by_id()
    return {"x": p.x, "v": p.v, "C": p.C, "F": p.F, "J": p.J, "steps": sim.steps, "dt": sim.dt,
            "history": [h["dt"] for h in sim.history]}, rewinds


def assert_same(a, b):
    for k in a:
        assert np.array_equal(np.asarray(a[k]), np.asarray(b[k])), k


@pytest.mark.parametrize("mode", ["original", "adaptive", "finest"])
def test_segments_give_the_particles_of_one_substep_at_a_time(two_parts, mode):
    """The CPU is deterministic and the math is unchanged: bit-identical, for eager
    segments and (where Warp replays CPU graphs) for captured ones."""
    scene, frames = sheet_scene(mode), 2
    one, _ = run_particles(scene, mode, frames, by_step=True)
    eager, _ = run_particles(scene, mode, frames, max_segment=SEGMENT_MAX)
    assert_same(one, eager)
    if cpu_graphs():
        captured, _ = run_particles(scene, mode, frames, max_segment=SEGMENT_MAX, capture=True)
        assert_same(one, captured)


def test_a_recut_inside_a_segment_rewinds_it_to_the_same_particles():
    scene = impact_scene()
    one, _ = run_particles(scene, None, 2)
    eager, rewinds = run_particles(scene, None, 2, max_segment=SEGMENT_MAX)
    assert rewinds and all(1 <= n < SEGMENT_MAX for n in rewinds)  # re-cuts in mid-segment
    assert_same(one, eager)
    if cpu_graphs():
        captured, rewinds = run_particles(scene, None, 2, max_segment=SEGMENT_MAX, capture=True)
        assert rewinds
        assert_same(one, captured)


def test_a_blow_up_inside_a_segment_stops_where_one_substep_at_a_time_stops(monkeypatch):
    """The run stops at the same step, with the same particles, whatever the segments."""
    from abmpm import simulation

    monkeypatch.setattr(simulation, "MIN_DT_FRACTION", 0.5)  # the impact counts as a blow-up
    results = []
    for max_segment in (1, SEGMENT_MAX):
        sim = abmpm.Simulation(impact_scene(), device="cpu")
        sim.max_segment = max_segment
        with pytest.raises(SimulationBlowUp) as err:
            sim.advance(frames=3)
        results.append((str(err.value), sim.steps, sim.particles().by_id().x))
    assert results[0][:2] == results[1][:2]
    assert np.array_equal(results[0][2], results[1][2])


def test_cuda_graph_is_a_scene_setting_ignored_on_the_cpu():
    scene = sheet_scene("original")
    scene = scene.model_copy(update={"simulation": scene.simulation.model_copy(update={"cuda_graph": True})})
    with pytest.warns(UserWarning, match="cuda_graph is ignored on the CPU"):
        sim = abmpm.Simulation(scene, device="cpu")
    assert not sim.solver.capture and sim.max_segment == 1
    assert not abmpm.SimulationSettings().cuda_graph  # off by default


# --------------------------------------------------------------------------- GPU


@pytest.mark.cuda
def test_captured_and_eager_segments_agree_on_cuda(cuda_available):
    if not cuda_available:
        pytest.skip("no CUDA device on this machine")
    runs = {}
    for capture in (False, True):
        scene = sheet_scene("adaptive")
        scene = scene.model_copy(update={"simulation": scene.simulation.model_copy(update={"cuda_graph": capture})})
        sim = abmpm.Simulation(scene, device="cuda")
        sim.max_segment = SEGMENT_MAX  # eager segments too: the same segment logic
        assert sim.solver.capture == capture
        signals = []
        for _ in range(3):
            sim._run_segment(sim.max_segment)
            signals.append(sim._signal)
        assert not capture or sim.solver._graphs
        runs[capture] = (sim.particles().by_id(), sim.steps, np.array(signals))
    (a, steps_a, sig_a), (b, steps_b, sig_b) = runs[False], runs[True]
    assert steps_a == steps_b and len(a) == len(b)
    # Same kernels with the same arguments in the same order; only the order of GPU
    # atomic adds in P2G differs between two runs (eager runs differ from each other
    # as much): float32 round-off, ~1e-7 relative per add, over 12 substeps. A wrong
    # dt, signal slot or stale buffer in a graph shows as >= one substep's motion
    # (~1e-4 m here) or as garbage.
    assert np.abs(a.x - b.x).max() <= 1e-6
    assert np.abs(a.v - b.v).max() <= 1e-4 * max(1.0, np.abs(a.v).max())
    assert np.allclose(sig_a, sig_b, rtol=1e-4)
