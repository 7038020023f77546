"""Running a sweep: one run (:func:`run_one`) and its headline row, the results
tables (``sweep.csv``, ``sweep.json``), the local loop and :func:`run_sweep`, which
hands the runs to :mod:`abmpm.sweep.cluster` when asked to use Ray."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import time
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from abmpm.errors import AbmpmError, OutOfMemory, SimulationBlowUp
from abmpm.io.atomic import atomic_write
from abmpm.io.outdir import prepare_out_dir
from abmpm.io.summary import write_json
from abmpm.runner import run
from abmpm.runtime import init_warp_silently
from abmpm.sweep.cluster import _init_ray, _sweep_on_ray, import_ray
from abmpm.sweep.plan import SweepPlan, feasible_on, format_value, plan_sweep, scene_source

CSV_FILE = "sweep.csv"
JSON_FILE = "sweep.json"

# Columns of a row, before the set values' and after them; then the headline figures.
_LEAD = ("run",)
_STATUS = ("status", "message")
# the keys of summary.json in a row (a list becomes key.0, key.1, ...)
_HEADLINE = (
    "mode",
    "device",
    "particle_count",
    "particle_count_per_level",
    "frames",
    "sim_time",
    "steps",
    "dt",
    "sim_seconds",
    "steps_per_second",
    "wall_seconds",
)
# the last entry of these per-frame series, as final.<name>
_FINAL = ("kinetic_energy", "potential_energy", "max_speed", "total_mass")


# --------------------------------------------------------------------------- one run


@contextlib.contextmanager
def _threads_env(threads: int | None) -> Iterator[None]:
    """ABMPM_THREADS=threads while a simulation is built (its solver reads it)."""
    if not threads:
        yield
        return
    old = os.environ.get("ABMPM_THREADS")
    os.environ["ABMPM_THREADS"] = str(int(threads))
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("ABMPM_THREADS", None)
        else:
            os.environ["ABMPM_THREADS"] = old


def _flatten(prefix: str, value: Any, out: dict) -> None:
    if isinstance(value, Mapping):
        for k, v in value.items():
            _flatten(f"{prefix}.{k}", v, out)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _flatten(f"{prefix}.{i}", v, out)
    else:
        out[prefix] = value


def headline(summary: Mapping | None) -> dict[str, Any]:
    """The headline figures of a run's summary, nested keys flattened with dots."""
    out: dict[str, Any] = {}
    if not summary:
        return out
    for key in _HEADLINE:
        if key in summary:
            _flatten(key, summary[key], out)
    series = summary.get("series") or {}
    for key in _FINAL:
        s = series.get(key) or []
        if s:
            _flatten(f"final.{key}", s[-1], out)
    return out


def _read_summary(out: Path) -> dict | None:
    try:
        return json.loads((out / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def run_one(
    scene,
    overrides: Mapping[str, Any],
    out: str | os.PathLike,
    frames: int | None = None,
    device: str | None = None,
    threads: int | None = None,
    preview: bool = True,
    name: str | None = None,
) -> dict[str, Any]:
    """Run ``scene`` (a SceneSource, Scene, plain dict, ``.toml`` path or built-in name)
    with ``overrides`` ({key: value}) into ``out`` in this process; return its row:
    ``run``, the set values, ``status`` (completed, blew_up, out_of_memory or error), ``message`` and
    the headline figures of its summary. A blow-up or an error is recorded, not raised
    (KeyboardInterrupt is)."""
    out = Path(out)
    row: dict[str, Any] = {"run": name or out.name, **dict(overrides), "status": "error", "message": None}
    summary = None
    try:
        sc = scene_source(scene).build(overrides)
        with _threads_env(threads):
            summary = run(sc, out, device=device, frames=frames, preview=preview, progress=False)
        row["status"] = summary.get("status", "completed")
        row["message"] = summary.get("message")
    except (SimulationBlowUp, OutOfMemory) as exc:
        summary = _read_summary(out)
        row["status"], row["message"] = ("blew_up" if isinstance(exc, SimulationBlowUp) else "out_of_memory"), str(exc)
    except AbmpmError as exc:
        row["message"] = " / ".join(str(exc).splitlines())
    except MemoryError:
        row["message"] = "out of memory; use a coarser grid (raise simulation.dx) or fewer particles"
    except Exception as exc:  # a bug in one run must not end the sweep: keep the traceback
        row["message"] = f"{type(exc).__name__}: {exc}"
        with contextlib.suppress(OSError):
            out.mkdir(parents=True, exist_ok=True)
            (out / "error.txt").write_text(traceback.format_exc(), encoding="utf-8")
            row["message"] += f" (traceback in {out / 'error.txt'})"
    row.update(headline(summary))
    return row


# --------------------------------------------------------------------------- results


def columns(rows: Sequence[Mapping], keys: Sequence[str]) -> list[str]:
    """CSV columns: run, the set keys, status, message, then every other column in
    the order first seen."""
    cols = list(_LEAD) + list(keys) + list(_STATUS)
    for row in rows:
        cols += [c for c in row if c not in cols]
    return cols


def _csv_cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, (list, tuple, bool, float)):
        return format_value(value)
    return str(value)


def write_results(out_dir: str | os.PathLike, rows: Sequence[Mapping], meta: Mapping[str, Any]) -> tuple[Path, Path]:
    """``sweep.csv`` and ``sweep.json`` in ``out_dir`` (atomic writes)."""
    out = Path(out_dir)
    keys = list(meta.get("set", {}))
    cols = columns(rows, keys)
    csv_path, json_path = out / CSV_FILE, out / JSON_FILE
    with atomic_write(csv_path) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(cols)
            for row in rows:
                w.writerow([_csv_cell(row.get(c)) for c in cols])
    write_json(json_path, {**meta, "columns": cols, "rows": [dict(r) for r in rows]})
    return csv_path, json_path


# --------------------------------------------------------------------------- the sweep


def run_sweep(
    scene,
    values: Mapping[str, Sequence[Any]],
    out_dir: str | os.PathLike,
    frames: int | None = None,
    device: str | None = None,
    threads: int | None = None,
    preview: bool = True,
    ray: str | None = None,
    on_start: Callable[[int, int, str], None] | None = None,
    on_done: Callable[[int, int, dict], None] | None = None,
    plan: SweepPlan | None = None,
) -> list[dict[str, Any]]:
    """Run every combination of ``values`` ({key: [v1, v2, ...]}) of ``scene`` into
    ``out_dir/<name>/``; write ``sweep.csv`` and ``sweep.json``; return the rows in
    the order of the combinations.

    ``ray=None`` runs them one after another in this process (``threads``: CPU threads
    per run, default $ABMPM_THREADS else every core). ``ray="auto"``, ``"local"`` or an
    address submits each as a Ray task asking for ``threads`` CPUs (default 1) or one
    GPU when the device is CUDA; an already initialised Ray connection is used as it
    is. ``on_start(i, n, name)`` / ``on_done(i, n, row)`` report progress
    (i counts from 1; with Ray, on_start when a run is submitted and on_done in the
    order the runs finish).
    """
    ray_mod = import_ray() if ray else None
    if plan is None:
        plan = plan_sweep(scene, values, check=None if ray else feasible_on(device))
    out = Path(out_dir).expanduser().resolve()
    started = _init_ray(ray_mod, ray) if ray_mod is not None else False  # before any folder is made
    try:
        return _sweep(plan, out, frames, device, threads, preview, ray, ray_mod, on_start, on_done)
    finally:
        if started:
            ray_mod.shutdown()


def _sweep(plan, out, frames, device, threads, preview, ray, ray_mod, on_start, on_done) -> list[dict]:
    prepare_out_dir(out)
    n = len(plan.runs)
    meta: dict[str, Any] = {
        "scene": plan.source.label,
        "set": plan.values,
        "frames": frames,
        "device": device,
        "threads": threads,
        "ray": ray,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    rows: list[dict | None] = [None] * n

    def done(i: int, row: dict) -> None:
        rows[i] = row
        write_results(out, [r for r in rows if r is not None], meta)  # a partial table survives a crash
        if on_done:
            on_done(i + 1, n, row)

    if ray_mod is None:
        for i, (name, combo) in enumerate(plan.runs):
            if on_start:
                on_start(i + 1, n, name)
            done(i, run_one(plan.source, combo, out / name, frames=frames, device=device,
                            threads=threads, preview=preview, name=name))
    else:
        _sweep_on_ray(ray_mod, _ray_run_one, plan, out, frames, device, threads, preview, on_start, done)
    final = [r for r in rows if r is not None]
    meta["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    write_results(out, final, meta)
    return final


def _ray_run_one(*args, **kwargs) -> dict[str, Any]:
    """run_one in a Ray worker: Warp quiet, as under the CLI."""
    init_warp_silently()
    return run_one(*args, **kwargs)
