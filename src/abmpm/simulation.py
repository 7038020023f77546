"""Public entry point: ``Simulation(scene).advance(frames=10)``.

Data flows one way: scene (validated description) -> geometry (particle samples)
-> simulation state on the device -> solver step -> host snapshots for output.
The Simulation owns time stepping (frames at a fixed rate, CFL substeps between),
diagnostics and the blow-up check. It reads no files itself except through
geometry's mesh loading of the scene's bodies.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_dilation

from .errors import AbmpmError, SimulationBlowUp
from .geometry.region import refinement_region
from .inputs import (material_rows, max_kinematic_viscosity, max_wave_speed, region_params, rigid_bodies, sample_scene,
                     solver_config)
from .runtime import MIN_DT_FRACTION, cfl_time_step, choose_device, init_warp  # noqa: F401 (init_warp: part of the API)
from .scene.model import Scene
from .sim.collider_set import ColliderSet
from .sim.diagnostics import first_non_finite, frame_diagnostics
from .sim.materials import uses_deformation_gradient
from .sim.refine import group_strays, merge_families
from .sim.solver import SEGMENT_MAX, MPMSolver
from .sim.state import DYNAMIC, STATIC, ParticleState, check_fields
from .sim.stiffness import SLACK as STIFFENING_SLACK
from .sim.time_levels import SLOW_STEP_COST, cut_for_levels

SORT_EVERY_FRAMES = 1  # particles are re-sorted by cell this often (memory coherence)
# particle fields renamed since earlier checkpoints were written
LEGACY_FIELDS = {"plastic": "history", "cp": "surface_point", "cn": "surface_side", "cbody": "surface_body"}


@dataclass(frozen=True)
class Particles:
    """Host copy of the particle state (numpy arrays, float32 / int32)."""

    x: np.ndarray
    v: np.ndarray
    mass: np.ndarray
    volume: np.ndarray
    material: np.ndarray
    level: np.ndarray
    id: np.ndarray
    family: np.ndarray  # id of the parent a split particle came from, else -1
    C: np.ndarray
    F: np.ndarray
    history: np.ndarray
    J: np.ndarray  # volume ratio V/V0: det(F) for solids, the tracked J for fluids

    def __len__(self) -> int:
        return len(self.x)

    def by_id(self) -> "Particles":
        """The same particles ordered by their stable id (the solver reorders them)."""
        order = np.argsort(self.id, kind="stable")
        return Particles(**{k: getattr(self, k)[order] for k in self.__dataclass_fields__})


def can_refine(scene: Scene) -> bool:
    """Whether an adaptive run of ``scene`` can ever split: it has boxes or a collider
    marked for refinement (with neither, adaptive mode is the original run)."""
    return bool(scene.simulation.refinement.boxes) or any(c.refine for c in scene.colliders)


class Simulation:
    """A running simulation of a :class:`~abmpm.scene.model.Scene`."""

    def __init__(self, scene: Scene, device: str | None = None, mode: str | None = None):
        if not isinstance(scene, Scene):
            raise TypeError(f"scene: expected an abmpm.Scene, got {type(scene).__name__} (a file or a built-in "
                            "name: abmpm.Simulation(abmpm.load_scene(...)))")
        for name, value in (("device", device), ("mode", mode)):
            if value is not None and not isinstance(value, str):
                raise TypeError(f"{name}: expected a string or None, got {value!r}")
        scene.check_feasible(mode, device)  # memory and time stepping (SceneError), before allocating
        init_warp()
        st = scene.simulation
        self.mode = mode or st.refinement.mode
        if self.mode not in ("original", "adaptive", "finest"):
            raise AbmpmError(f"unknown mode {self.mode!r} (use original, adaptive or finest)")
        b = st.refinement.factor
        if self.mode == "finest":
            # the whole domain at dx/b, particles sampled at the fine spacing
            st = st.model_copy(update={"dx": st.dx / b})
            scene = scene.model_copy(update={"simulation": st})
        self.scene = scene
        # per material: keeps no F, its volume ratio J in ``history`` (fluids)
        self._j_in_history = np.array([not uses_deformation_gradient(m.model) for m in scene.materials])
        self.device = choose_device(device if device is not None else st.device)
        self.frame_dt = 1.0 / st.fps
        self.dx = st.dx  # spacing of the coarsest grid
        self.colliders = ColliderSet(rigid_bodies(scene), self.device, cpic=st.cpic) if scene.colliders else None
        self.wave_speed = max_wave_speed(scene)
        self.viscosity = max_kinematic_viscosity(scene)  # m^2/s: the viscous step limit
        self.solver = MPMSolver(solver_config(scene, self.mode), material_rows(scene), self.device, self.colliders)
        # The most substeps between two host points (one read of their CFL signals):
        # 1 unless the solver replays captured graphs. Any value gives the results of
        # one substep at a time: a segment that must stop early is rewound.
        self.max_segment = SEGMENT_MAX if self.solver.capture else 1
        arrays = sample_scene(scene, b if self.mode == "adaptive" and can_refine(scene) else 1)
        if self.mode == "finest":
            arrays["level"][:] = 1
        self._load_arrays(arrays)
        self.solver.reserve_ids(len(arrays["x"]))
        if self.mode == "adaptive":
            self.solver.set_region(self.refinement_cells(), self._state)
        self.frame = 0
        self.steps = 0
        self._t_frame = 0.0  # time since the frame started
        self._taken = 0  # substeps taken in this frame
        self.history: list[dict] = []
        self._slow_signal = (0.0, 1.0)  # the slow set's last CFL signal (a time step per level)
        self._signal_all = True  # the last substep's signal came from every particle
        # a step shorter than this fraction of the step at rest means the run has blown up
        self._min_dt = MIN_DT_FRACTION * self.cfl_dt(0.0)
        self.solver.sort_by_cell(self._state)
        self._choose_dt((float(np.sqrt((arrays["v"].astype(np.float64) ** 2).sum(axis=1)).max()), 1.0))
        self.solver.color_particles(self._state)
        self._keep_last_good(self._state.numpy())
        self.history.append(self._diagnostics(self._last_good))

    # ------------------------------------------------------------------ time stepping

    def _load_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        self._state = ParticleState.from_numpy(arrays, self.device)

    def cfl_dt(self, max_speed: float, stiffening: float = 1.0, dx: float | None = None) -> float:
        """CFL step on the finest active spacing for the wave speed plus the fastest
        particle, capped by max_dt and by the viscous limit. Where a fluid is compressed its sound speed is
        ``stiffening`` times the speed at rest; up to STIFFENING_SLACK of that is taken
        from the margin of the CFL number (the effective CFL number there stays below
        cfl * STIFFENING_SLACK = 0.8 by default), beyond it the step shrinks. ``dx``:
        another spacing (the slow set's, the coarse one)."""
        st = self.scene.simulation
        c = self.wave_speed * max(1.0, stiffening / STIFFENING_SLACK)
        return cfl_time_step(st.cfl, st.max_dt, dx or self.solver.finest_active_dx, c + max_speed, self.viscosity)

    def _choose_dt(self, signal: tuple[float, float]) -> None:
        """At a frame start: the CFL step, shortened so that a whole number of equal
        substeps fills the frame."""
        self._signal = signal
        self._split_rest(self.frame_dt, self.cfl_dt(*signal))
        self.substeps = self._left

    def _split_rest(self, rest: float, dt_max: float) -> None:
        # the rest of the frame in equal substeps no longer than dt_max
        solver = self.solver
        self._left = max(1, math.ceil(rest / dt_max - 1e-9))
        if solver.slow is not None:
            # A time step per level (sim/time_levels.py): the slow set takes one step per k
            # substeps of the fast set, as many as fit in its own CFL step (coarse spacing,
            # its own speed; k <= the refinement period), the substeps shortened where
            # that is cheaper (``cut_for_levels``)
            if self._signal_all:  # the slow set stepped with everyone: its speed is in the last signal
                self._slow_signal = self._signal
            slow_dt, nodes = self._slow_dt(), math.prod(solver.grid.dims)
            # the sorts choose the slow set only where its step could pay (on a GPU that
            # choice is a host round trip per sort): a step longer than SLOW_STEP_COST substeps
            solver.choose_slow = slow_dt * self._left > SLOW_STEP_COST * rest
            self._left, solver.block = cut_for_levels(rest, dt_max, slow_dt, SEGMENT_MAX,
                                                      solver.slow_count, solver.fast_cost(), nodes)
        self.dt = rest / self._left

    def _checked_dt(self, signal: tuple[float, float]) -> float:
        """The CFL step for the last substep's signal (fastest particle, fluid
        stiffening); stops the run if a velocity is not finite or the step has
        collapsed."""
        max_speed, stiffening = signal
        if not (math.isfinite(max_speed) and math.isfinite(stiffening)) or max_speed >= 1.0e29:
            self._blow_up("a particle velocity became NaN/inf")
        dt_max = self.cfl_dt(*signal)
        if dt_max < self._min_dt:
            self._blow_up(
                f"max speed {max_speed:.3g} m/s (sound speed x{stiffening:.3g} where compressed) "
                f"needs a time step below {self._min_dt:.3g} s "
                f"({MIN_DT_FRACTION:g} of the step at rest). Lower the impact speed, the "
                f"collider separation or the stiffness, or refine less"
            )
        return dt_max

    def _blow_up(self, why: str) -> None:
        raise SimulationBlowUp(
            f"simulation blew up at step {self.steps} (t = {self.time:.4f} s): {why}; "
            f"last good frame is {self.history[-1]['frame']}"
        )

    def refinement_cells(self) -> np.ndarray:
        """Refined coarse cells B_s now: narrow free space and moving edges of the
        colliders marked for refinement, or their boundary density (Eqs. 26-27),
        as ``refinement.criterion`` says, plus the scene's boxes."""
        g = self.solver.grid
        meshes = self.colliders.body_meshes() if self.colliders is not None else []
        flags = [c.refine for c in self.scene.colliders]
        moving = [not c.motion.is_static for c in self.scene.colliders]
        cells, _ = refinement_region(meshes, flags, g.origin, g.dx, np.array(g.dims), region_params(self.scene),
                                     moving_flags=moving)
        return cells

    @property
    def time(self) -> float:
        return self.frame * self.frame_dt + self._t_frame

    @property
    def substep(self) -> int:
        """Substeps taken in the current frame."""
        return self._taken

    @property
    def particle_count(self) -> int:
        return self._state.count

    def step(self) -> None:
        """One substep of length ``self.dt``; its fastest particle sets the next
        substep's length (CFL); frame bookkeeping when a frame completes.

        An impact can multiply speeds within a frame, so the rest of the frame is
        re-cut whenever the current step has become too long; a frame with steady
        speeds keeps equal substeps."""
        self._run_segment(1)

    def _slow_dt(self) -> float:
        # the slow set's CFL step: the coarse spacing, its own fastest particle and stiffening
        return self.cfl_dt(*self._slow_signal, dx=self.dx)

    def _close_slow(self, recut: bool = False) -> None:
        # the slow set's step ends (sim/time_levels.py); its speed is checked like the
        # others'; with ``recut``, a slow set now too fast for its step re-cuts the frame
        signal = self.solver.close_slow(self._state)
        if signal is None:
            return
        self._slow_signal = signal
        self._checked_dt(signal)
        if recut and self.dt * self.solver.block > self._slow_dt() * (1.0 + 1e-6):
            self._split_rest(self.frame_dt - self._t_frame, self.cfl_dt(*self._signal))
            self.substeps = self._taken + self._left

    def _run_segment(self, limit: int, done=None) -> None:
        """Up to ``limit`` substeps as one segment of the solver (no host work between
        them), then each substep's bookkeeping in turn, as ``step`` does it. Should a
        substep end the segment early (the rest of the frame re-cut, a blow-up, or
        ``done()``), the solver rewinds to just after it: any ``limit`` gives the
        results of one substep at a time."""
        if self.solver.slow_due:
            self._close_slow(recut=True)
        n = min(limit, self._left, self.solver.segment_length)
        self.solver.begin_segment(self._state, self.time, self.dt, n)
        self.solver.run_segment(self._state)
        signals = self.solver.end_segment()
        for k in range(n):
            early = k < n - 1
            try:
                recut = self._substep_taken((float(signals[k, 0]), float(signals[k, 1])))
            except SimulationBlowUp:
                if early:
                    self.solver.rewind(self._state, k + 1)
                raise
            if early and (recut or (done is not None and done())):
                self.solver.rewind(self._state, k + 1)
                return

    def _substep_taken(self, signal: tuple[float, float]) -> bool:
        # bookkeeping after one substep; True if the rest of the frame was re-cut
        self.steps += 1
        self._taken += 1
        self._left -= 1
        self._t_frame += self.dt
        self._signal = signal
        self._signal_all = self.solver.block < 2 or self.solver.slow_count == 0
        dt_max = self._checked_dt(signal)
        if self._left == 0:
            self._t_frame = 0.0
            self._taken = 0
            self._close_slow()
            with self.solver.section("frame end"):  # a phase of a profile (abmpm bench --profile)
                self._end_frame()
        elif self.dt > dt_max * (1.0 + 1e-6):
            self._close_slow()
            self._split_rest(self.frame_dt - self._t_frame, dt_max)
            self.substeps = self._taken + self._left
            return True
        return False

    def advance(self, seconds: float | None = None, frames: int | None = None, callback=None) -> None:
        """Run whole frames, or a duration in seconds (stopping at the first substep
        boundary at or after it). ``callback(sim)`` is called after every frame."""
        if (seconds is None) == (frames is None):
            raise ValueError("give exactly one of seconds= or frames=")
        if frames is not None:
            if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 0:
                raise ValueError(f"frames= must be a whole number >= 0, got {frames!r}")
            target = self.frame + int(frames)
            done = lambda: self.frame >= target  # noqa: E731
        else:
            if isinstance(seconds, bool) or not isinstance(seconds, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(seconds) or seconds < 0:
                raise ValueError(f"seconds= must be a finite number >= 0, got {seconds!r}")
            t_end = self.time + float(seconds)
            done = lambda: self.time >= t_end - 1e-9 * max(1.0, t_end)  # noqa: E731
        while not done():
            frame = self.frame
            self._run_segment(self.max_segment, done)
            if callback is not None and self.frame != frame:
                callback(self)

    def _end_frame(self) -> None:
        snap = self._state.numpy()
        self.frame += 1
        bad = first_non_finite(snap)
        if bad is not None:
            self.frame -= 1
            raise SimulationBlowUp(
                f"simulation blew up at step {self.steps} (t = {self.frame * self.frame_dt + self.frame_dt:.4f} s): "
                f"particle field '{bad}' became NaN/inf; last good frame is {self.frame}"
            )
        dt = self.dt  # the frame's last step (the diagnostics'), before the next frame's is chosen
        self._choose_dt(self._signal)  # the step's signal was checked in step()
        changed = False  # the particles since snap
        if self.mode == "adaptive" and any(c.refine and not c.motion.is_static for c in self.scene.colliders):
            self.solver.set_region(self.refinement_cells())  # the region follows moving colliders (per frame)
        if self.mode == "adaptive" and self.scene.simulation.refinement.merge:
            changed = self._merge(snap)
        if self.frame % SORT_EVERY_FRAMES == 0:
            self.solver.sort_by_cell(self._state)
            changed = True
        if self.solver.slow is not None:  # the slow set's share follows the sort
            self._choose_dt(self._signal)
        # what a checkpoint of this frame holds, also when the next frame fails or is interrupted,
        # and what its diagnostics describe (the particles its PLY frame holds: after the merge)
        self._keep_last_good(self._state.numpy() if changed else snap)
        self.history.append(self._diagnostics(self._last_good, dt))

    def _keep_last_good(self, snap: dict[str, np.ndarray]) -> None:
        self._last_good, self._last_good_signal = snap, self._signal
        self._last_good_ids, self._last_good_slow = self.solver.next_id, self._slow_signal

    def _merge(self, snap: dict[str, np.ndarray]) -> bool:
        """Merge families that left the region (by the margin) back into level-0 particles,
        then the strays of torn fluid families by place (whether any merged)."""
        r = self.scene.simulation.refinement
        region = self.solver.region
        if r.merge_margin:
            region = binary_dilation(region, iterations=r.merge_margin)

        def keep_fine(a: dict[str, np.ndarray]) -> np.ndarray:
            # in the region (and margin), or touching a collider (it carries a color: within the
            # particle band of a surface), where a coarse particle would stand a coarse cell's
            # contact distance off it (a blade's faces, which the region leaves coarse)
            cell = np.clip(((a["x"] - self.solver.grid_origin) / self.dx).astype(int), 0, np.array(region.shape) - 1)
            return region[cell[:, 0], cell[:, 1], cell[:, 2]] | (a["surface_body"] >= 0)

        merged, n = merge_families(snap, keep_fine(snap), r.factor)
        if r.merge_strays:
            keep = keep_fine(merged)
            family, groups = group_strays(merged, keep, r.factor, self._j_in_history, self.solver.grid_origin)
            if groups:
                merged, more = merge_families({**merged, "family": family}, keep, r.factor)
                n += more
        if n:
            self._load_arrays(merged)
            self.solver.adopt(self._state)
        return n > 0

    # ------------------------------------------------------------------ inspection

    def _diagnostics(self, snap: dict[str, np.ndarray], dt: float | None = None) -> dict:
        d = frame_diagnostics(snap, self._level_dx, self.scene.simulation.gravity)
        d.update(frame=self.frame, time=self.frame * self.frame_dt, steps=self.steps, dt=self.dt if dt is None else dt)
        return d

    @property
    def _level_dx(self) -> dict[int, float]:
        return self.solver.level_spacings

    def particles(self) -> Particles:
        return self._particles(self._state.numpy())

    def _particles(self, arrays: dict[str, np.ndarray]) -> Particles:
        # models without F (fluid) keep their volume ratio J in ``history``
        j_in_history = self._j_in_history[arrays["material"]]
        J = np.linalg.det(arrays["F"].astype(np.float64)).astype(np.float32)
        J[j_in_history] = arrays["history"][j_in_history]
        fields = {k: arrays[k] for k in Particles.__dataclass_fields__ if k != "J"}
        return Particles(J=J, **fields)

    def collider_triangles(self, time: float | None = None) -> np.ndarray:
        """(M, 3, 3) world-space collider triangles at ``time`` (default: now); empty
        without colliders. For rendering and export."""
        if self.colliders is None:
            return np.zeros((0, 3, 3))
        return self.colliders.triangles(self.time if time is None else time)

    def refined_region(self) -> dict | None:
        """The refined coarse cells now (adaptive mode): ``cells`` (bool, one per coarse
        cell), ``origin`` (corner of cell (0,0,0)) and ``dx``; None in other modes."""
        cells = self.solver.region
        if cells is None:
            return None
        return {"cells": cells, "origin": self.solver.grid_origin, "dx": self.dx}

    def collider_faces(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(vertices at the current time, faces) of all colliders, or None."""
        if self.colliders is None:
            return None
        return self.colliders.vertices(self.time), self.colliders.faces

    def diagnostics(self) -> dict:
        """Mass, momentum, angular momentum, kinetic energy, max speed, count, now."""
        d = frame_diagnostics(self._state.numpy(), self._level_dx, self.scene.simulation.gravity)
        d.update(frame=self.frame, time=self.time, steps=self.steps, dt=self.dt)
        return d

    def set_particles(self, **arrays: np.ndarray) -> None:
        """Overwrite per-particle fields (e.g. ``v=...``), given in particle-id order
        (the order of ``particles().by_id()``)."""
        self._close_slow()
        current = self._state.numpy()
        slot = np.argsort(current["id"], kind="stable")  # slot[id] = index in the state
        for k, a in arrays.items():
            if k not in current or k == "id":
                raise KeyError(f"unknown or read-only particle field {k!r}")
            if np.shape(a) != current[k].shape:
                raise ValueError(f"{k}: expected shape {current[k].shape}, got {np.shape(a)}")
        st = self.scene.simulation  # positions within a cell of the domain (the walls' own round-off passes)
        check_fields(arrays, len(self.scene.materials), len(self.scene.colliders), self._levels(),
                     (np.subtract(st.domain_min, st.dx), np.add(st.domain_max, st.dx)))
        for k, a in arrays.items():
            current[k][slot] = np.asarray(a, dtype=current[k].dtype)
        self._load_arrays(current)
        self.solver.adopt(self._state)

    def _levels(self) -> tuple[int, ...]:
        # the particle levels this mode has a grid for
        return {"original": (0,), "finest": (1,)}.get(self.mode, (0, 1))

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self, last_good: bool = False) -> tuple[dict[str, np.ndarray], dict]:
        """Arrays and metadata to resume from (at a frame boundary)."""
        if self.substep != 0 and not last_good:  # the last good state is always a frame boundary
            raise RuntimeError("checkpoints are taken at frame boundaries")
        arrays = dict(self._last_good) if last_good else self._state.numpy()
        frame = self.history[-1]["frame"] if last_good else self.frame
        meta = {
            "frame": frame,
            "steps": self.history[-1]["steps"] if last_good else self.steps,
            "dt": self.dt,
            "substeps": self.substeps,
            # fastest particle and fluid stiffening at that frame: they set the next time step
            "cfl_signal": list(self._last_good_signal if last_good else self._signal),
            "slow_signal": list(self._last_good_slow if last_good else self._slow_signal),
            "history": [h for h in self.history if h["frame"] <= frame],
            "scene": self.scene.name,
            "mode": self.mode,
            "next_id": self._last_good_ids if last_good else self.solver.next_id,
        }
        return arrays, meta

    def load_state_dict(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        arrays = {LEGACY_FIELDS.get(k, k): a for k, a in arrays.items()}
        missing = [k for k in DYNAMIC + STATIC if k not in arrays]
        if missing:
            raise AbmpmError(f"checkpoint lacks particle fields: {', '.join(missing)}")
        if meta.get("mode", self.mode) != self.mode or not {"frame", "steps", "history"} <= set(meta):
            raise AbmpmError(f"the checkpoint is of a {meta.get('mode', '?')} run with metadata {sorted(meta)}; "
                             f"this simulation is in {self.mode} mode")
        try:
            if len({len(arrays[k]) for k in DYNAMIC + STATIC}) != 1:
                raise ValueError("its particle fields differ in length")
            check_fields(arrays, len(self.scene.materials), len(self.scene.colliders), self._levels())
        except ValueError as exc:
            raise AbmpmError(f"checkpoint: {exc} (another scene's?)") from None
        self._load_arrays({k: arrays[k] for k in DYNAMIC + STATIC})
        self.frame = int(meta["frame"])
        self.steps = int(meta["steps"])
        self._t_frame = 0.0
        self._taken = 0
        self.history = list(meta["history"])
        if "cfl_signal" in meta:
            self._choose_dt(tuple(float(a) for a in meta["cfl_signal"]))
        else:  # checkpoints written before the per-substep CFL
            self.dt, self.substeps = float(meta["dt"]), int(meta["substeps"])
            self._left, self._signal = self.substeps, (0.0, 1.0)
        self.solver.reserve_ids(int(meta.get("next_id", self.solver.next_id)))
        self.solver.reset_step_count(self.steps)
        self.solver.adopt(self._state, recolor=False)  # its colors are the run's: bit-identical
        if self.solver.slow is not None:
            self._slow_signal = tuple(float(a) for a in meta.get("slow_signal", self._signal))
            self._signal_all = False
            self._choose_dt(self._signal)
        self._keep_last_good(self._state.numpy())
