"""Running the modes of a scene and measuring each run (see :mod:`abmpm.compare`)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from abmpm.compare.outcomes import leaks, outcome_for
from abmpm.compare.paper import PAPER_CONTACT, PAPER_SCENES, QUICK_OVERRIDES
from abmpm.compare.report import scene_figures, write_report
from abmpm.errors import AbmpmError, OutOfMemory, OutputError, SimulationBlowUp
from abmpm.io.outdir import scene_from_folder
from abmpm.post.preview import disk_frames
from abmpm.runner import run
from abmpm.scene.checks import MAX_FRAMES
from abmpm.scene.loader import load_scene
from abmpm.scene.model import with_mode
from abmpm.sweep import scene_source

MODES = ("original", "adaptive", "finest")
TABLE_FILE = "table1.json"
REPORT_FILE = "report.md"


def apply_overrides(scene, overrides: dict):
    """The scene with dotted keys (``simulation.dx``, ``colliders.0.text``) set, validated
    again like a scene file (the same overrides as ``abmpm sweep --set``)."""
    return scene_source(scene).build(overrides, label=f"{scene.name} (overridden)")


def quick_scene(scene):
    """The ``--quick`` version of a paper scene (unchanged for other scenes)."""
    return apply_overrides(scene, QUICK_OVERRIDES[scene.name]) if scene.name in QUICK_OVERRIDES else scene


def check_modes(modes) -> tuple[str, ...]:
    modes = tuple(modes)
    bad = [m for m in modes if m not in MODES]
    if bad or not modes:
        raise AbmpmError(f"unknown mode {bad[0] if bad else '(none)'!r} (known: {', '.join(MODES)})")
    return modes


class FrameSeq(Sequence):
    """``[(time, frame dict)]`` of a run folder's PLY frames, read when asked for (a
    paper-scale finest run has too many particles to hold every frame at once); the
    last two frames read are kept."""

    def __init__(self, items: list):
        self.items = items
        self._cache: dict[int, dict] = {}

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return FrameSeq(self.items[i])
        i = range(len(self.items))[i]
        if i not in self._cache:
            if len(self._cache) >= 2:
                self._cache.pop(next(iter(self._cache)))
            self._cache[i] = self.items[i][1]()
        return self.items[i][0], self._cache[i]


def _load_frames(run_dir: Path, fps: float) -> FrameSeq:
    return FrameSeq([(n / fps, load) for n, load in disk_frames(run_dir)])


def window_figures(series: dict, first_frame: int) -> dict | None:
    """Speed and particles over the frames from ``first_frame`` to the last one (the
    summary's per-frame ``steps`` and ``sim_seconds``); None when the run did not get
    past ``first_frame`` or the window's clock is missing (frames of a resumed run)."""
    times, steps, clock = (series.get(k) or [] for k in ("time", "steps", "sim_seconds"))
    counts = series.get("count_per_level") or []
    n = min(len(times), len(steps), len(clock), len(counts))
    if first_frame >= n - 1 or clock[first_frame] is None or clock[n - 1] is None:
        return None
    seconds = clock[n - 1] - clock[first_frame]
    taken = steps[n - 1] - steps[first_frame]
    return {
        "start": float(times[first_frame]),
        "end": float(times[n - 1]),
        "steps": int(taken),
        "sim_seconds": round(seconds, 3),
        "steps_per_second": round(taken / seconds, 2) if seconds > 0 else None,
        "wall_seconds_per_sim_second": seconds / (times[n - 1] - times[first_frame]),
        # particles at the window's frames after its first (the steps timed ran between them)
        "particles_mean": float(np.mean([sum(c) for c in counts[first_frame + 1:n]])),
        "particles_end": int(sum(counts[n - 1])),
    }


def measure(scene, run_dir: Path, summary: dict, window_from: int | None = None) -> dict:
    """The record of one run: particles, speed, outcome figures and leaks; with
    ``window_from`` (a frame) also ``window``, the speed from that frame on."""
    st = scene.simulation
    mode = st.refinement.mode
    series = summary.get("series") or {}
    counts = [sum(c) for c in series.get("count_per_level") or [] if c is not None]
    sim_time = float(summary.get("sim_time") or 0.0)
    frames = _load_frames(run_dir, st.fps)
    rec = {
        "scene": scene.name,
        "mode": mode,
        "status": summary.get("status"),
        "dx": st.dx,
        "dx_fine": st.dx / st.refinement.factor,
        "frames": summary.get("frames"),
        "sim_time": sim_time,
        "particles_mean": float(np.mean(counts)) if counts else None,
        "particles_end": int(counts[-1]) if counts else summary.get("particle_count"),
        "steps": summary.get("steps"),
        "steps_per_second": summary.get("steps_per_second"),
        "sim_seconds": summary.get("sim_seconds"),
        "wall_seconds": summary.get("wall_seconds"),
        "wall_seconds_per_sim_second": (summary["wall_seconds"] / sim_time
                                        if sim_time > 0 and summary.get("wall_seconds") else None),
        "device": summary.get("device"),
        "run_dir": str(run_dir),
    }
    if window_from is not None:
        rec["window"] = window_figures(series, window_from)
    if frames:
        rec["outcome"] = outcome_for(scene)(scene, frames, summary)
        rec["leaks"] = leaks(scene, frames)
    else:
        rec["outcome"], rec["leaks"] = {"series": {}, "final": {}}, {}
    return rec


def read_table(out: Path, strict: bool = False) -> list[dict]:
    """The records of ``out/table1.json`` ([] where there is none). An unreadable or
    foreign file reads as none, or with ``strict`` (``--remeasure``, which has nothing else
    to go on) is an error naming it."""
    path = Path(out) / TABLE_FILE
    if not path.exists():
        return []
    try:
        records = json.loads(path.read_text()).get("records", [])
        if not isinstance(records, list) or not all(isinstance(r, dict) and "run_dir" in r for r in records):
            raise ValueError("its records are not those of abmpm compare")
        return records
    except (OSError, ValueError, AttributeError) as exc:
        if strict:
            why = "not a JSON object" if isinstance(exc, AttributeError) else exc
            raise AbmpmError(f"{path}: cannot be read ({why})") from None
        return []


def _read_summary(run_dir: Path) -> dict:
    path = run_dir / "summary.json"
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise AbmpmError(f"{path}: cannot be read ({exc})") from None
    if not isinstance(summary, dict):
        raise AbmpmError(f"{path}: not a run's summary (a JSON object)")
    return summary


def write_table(out: Path, records: list[dict]) -> Path:
    path = Path(out) / TABLE_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"records": records}, indent=1, default=float))
    return path


def compare(scene, modes=MODES, out="out/compare", frames: int | None = None, duration: float | None = None,
            overrides: dict | None = None, quick: bool = False, device: str | None = None,
            progress: bool = False, on_run=None, window: tuple[float, float] | None = None) -> list[dict]:
    """Run ``scene`` (a Scene, file or built-in name) in each of ``modes`` into
    ``out/<scene>/<mode>/``, measure every run, merge the records into
    ``out/table1.json`` (replacing earlier records of the same scene and mode) and write
    ``out/report.md``. ``quick`` applies :data:`QUICK_OVERRIDES`; ``overrides`` are more
    dotted keys; ``duration`` sets ``simulation.duration``; ``window`` = (contact
    time, seconds) runs to that long after contact instead of ``frames`` and times the
    frames from contact on apart (:func:`window_frames`, :func:`window_figures`).
    Returns this scene's records."""
    modes = check_modes(modes)
    base = load_scene(scene)
    if quick:
        base = quick_scene(base)
    extra = dict(overrides or {})
    if duration is not None:
        extra["simulation.duration"] = duration
    if extra:
        base = apply_overrides(base, extra)
    window_from = None
    if window is not None:
        window_from, frames = window_frames(*window, base.simulation.fps)
        if frames > MAX_FRAMES:
            raise AbmpmError(f"--window {window[1]:g} s: {frames:.3g} frames at {base.simulation.fps:g} fps, "
                             f"more than {MAX_FRAMES:.0e}")
    out = Path(out)
    records = []
    for i, mode in enumerate(modes):
        sc = with_mode(base, mode)
        run_dir = out / base.name / mode
        if on_run:
            on_run(i + 1, len(modes), base.name, mode, run_dir)
        try:
            summary = run(sc, run_dir, device=device, frames=frames, preview=False, progress=progress)
        except (SimulationBlowUp, OutOfMemory) as exc:  # recorded; the other modes still run
            status = "blew_up" if isinstance(exc, SimulationBlowUp) else "out_of_memory"
            summary = json.loads((run_dir / "summary.json").read_text()) if (run_dir / "summary.json").exists() \
                else {"status": status, "message": str(exc)}
        rec = measure(sc, run_dir, summary, window_from)
        rec["quick"] = bool(quick and base.name in QUICK_OVERRIDES)
        records.append(rec)
    table = [r for r in read_table(out) if not (r.get("scene") == base.name and r.get("mode") in modes)]
    _write_outputs(out, table + records, [(base, records, base.name)])
    return records


def remeasure(out) -> list[dict]:
    """Measure the runs recorded in ``out/table1.json`` again from their folders (their
    ``scene.json``, ``summary.json`` and frames) and rewrite the figures, the table
    and the report: for a changed outcome function, without running anything. No
    table there: nothing is written, and the answer is empty."""
    out = Path(out)
    table, scenes = [], {}
    recorded = read_table(out, strict=True)
    if not recorded:
        return []
    for old in recorded:
        run_dir = Path(old["run_dir"])
        sc = scene_from_folder(run_dir)
        rec = measure(sc, run_dir, _read_summary(run_dir))
        rec["quick"] = old.get("quick", False)
        table.append(rec)
        scenes.setdefault(rec["scene"], sc)
    _write_outputs(out, table, [(sc, [r for r in table if r["scene"] == name], name) for name, sc in scenes.items()])
    return table


def _write_outputs(out: Path, table: list[dict], figures: list) -> None:
    # the figures of each (scene, its records, its folder's name), the table and the report
    try:
        for sc, records, name in figures:
            scene_figures(sc, records, out / name)
        write_table(out, table)
        write_report(out, table)
    except OSError as exc:
        raise OutputError(f"cannot write the comparison in {out}: {exc.strerror or exc}") from None


def check_window(window: float) -> None:
    if not math.isfinite(window) or window <= 0.0:
        raise AbmpmError(f"--window must be a positive number of seconds, got {window}")


def window_frames(contact: float, window: float, fps: float) -> tuple[int, int]:
    """``(first, frames)`` of a window of ``window`` seconds after ``contact`` (a time,
    e.g. the scene's :data:`PAPER_CONTACT`): the first output frame at or after
    contact, and the frames to run so that the window follows it."""
    check_window(window)
    first = math.ceil(contact * fps - 1e-9)
    return first, first + max(1, round(window * fps))


def run_paper(scenes=PAPER_SCENES, modes=MODES, out="out/paper", quick: bool = False, frames: int | None = None,
              overrides: dict | None = None, device: str | None = None, progress: bool = False,
              on_run=None, window: float | None = None) -> list[dict]:
    """:func:`compare` for each of the paper's scenes (``overrides`` apply to all).
    ``window`` (seconds; instead of ``frames``) runs each scene to ``window`` seconds
    after its contact time and times that window apart (``window`` in the records)."""
    scenes = tuple(scenes)
    bad = [s for s in scenes if s not in PAPER_SCENES]
    if bad or not scenes:
        raise AbmpmError(f"unknown paper scene {bad[0] if bad else '(none)'!r} (known: {', '.join(PAPER_SCENES)})")
    check_modes(modes)
    if window is not None:
        if frames is not None:
            raise AbmpmError("--window and --frames: give one of them")
        check_window(window)  # before anything runs
    records = []
    for name in scenes:
        records += compare(name, modes, out, frames=frames, overrides=overrides, quick=quick, device=device,
                           progress=progress, on_run=on_run,
                           window=None if window is None else (PAPER_CONTACT[name], window))
    return records
