"""``summary.json`` (run statistics and per-frame diagnostics) and ``energy.png``
(kinetic, potential and total energy; mass and momentum)."""

from __future__ import annotations

import time

import numpy as np
import warp as wp

import abmpm
from abmpm.io.outdir import ENERGY_FILE, SCENE_FILE, SUMMARY_FILE, numbered_outputs
from abmpm.io.summary import write_json
from abmpm.io.writers.base import RunContext, Writer
from abmpm.post.plots import plot_energy

SERIES = ("time", "steps", "kinetic_energy", "potential_energy", "total_mass", "momentum", "max_speed",
          "count_per_level")


def series(history: list[dict], clock: dict[int, float] | None = None) -> dict[str, list]:
    """The per-frame diagnostics as one list per quantity. ``clock`` (frame -> seconds
    of simulation since this run began, output excluded) adds ``sim_seconds``: None
    for frames of an earlier run (before a resume), so that a window of frames can be
    timed (``abmpm paper --window``)."""
    out = {k: [h.get(k) for h in history] for k in SERIES}
    if clock is not None:
        out["sim_seconds"] = [clock.get(int(h["frame"])) for h in history]
    return out


def versions() -> dict[str, str]:
    return {"abmpm": getattr(abmpm, "__version__", "?"), "numpy": np.__version__, "warp": wp.config.version}


def make_summary(
    run: RunContext, message: str | None, sim_seconds: float, output_seconds: float, steps: int
) -> dict:
    """The summary of a run that has stopped (``run.status`` set); ``steps`` is the
    number of substeps this run took. The writers' ``finish`` completes it."""
    sim, scene = run.sim, run.scene
    last = sim.history[-1]
    return {
        "scene": scene.name,
        "description": scene.description,
        "status": run.status,
        "message": message,
        "device": str(sim.device),
        "mode": sim.mode,
        "particle_count": int(sim.particle_count),
        "particle_count_per_level": [int(c) for c in last["count_per_level"]],
        "frames": int(last["frame"]),  # last completed (good) frame
        "frames_requested": run.total,
        "fps": scene.simulation.fps,
        "sim_time": float(last["time"]),
        "steps": int(last["steps"]),
        "dt": float(sim.dt),
        "substeps": int(sim.substeps),
        "resumed_from_frame": run.resumed_from,
        "sim_seconds": round(sim_seconds, 3),
        "steps_per_second": round(steps / sim_seconds, 2) if sim_seconds > 0 else None,
        "output_seconds": round(output_seconds, 3),
        "render_seconds": None,
        "wall_seconds": None,
        "versions": versions(),
        "outputs": {},
        "series": series(sim.history, run.clock),
    }


class EnergyPlotWriter(Writer):
    """``energy.png`` from the summary's series (not for an interrupted run)."""

    name = "energy"

    def finish(self, run: RunContext) -> None:
        if run.interrupted:
            return

        title = f"{run.scene.name}: energy and conservation"
        plot_energy(run.summary["series"], run.out / ENERGY_FILE, title=title)
        run.outputs["energy_plot"] = ENERGY_FILE


class SummaryWriter(Writer):
    """``summary.json``: ``run.summary`` with the list of outputs; the last writer."""

    name = "summary"

    def finish(self, run: RunContext) -> None:
        summary = run.summary
        # the numbered files as they are on disk: after a resume, the earlier run's too
        summary["outputs"] = {"scene": SCENE_FILE, "summary": SUMMARY_FILE, **numbered_outputs(run.out), **run.outputs}
        if not run.interrupted:
            summary["render_seconds"] = round(run.render_seconds, 3)
        summary["wall_seconds"] = round(time.perf_counter() - run.t_start, 3)
        write_json(run.out / SUMMARY_FILE, summary)
