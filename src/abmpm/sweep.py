"""Wedges (parameter sweeps): run a scene once per combination of set values.

``abmpm sweep dam_break --set simulation.dx=0.02,0.01 --set simulation.refinement.mode=original,adaptive``
runs the Cartesian product of the values (like a Houdini wedge), each into a folder
of its own named from the values, and writes one row per run to ``sweep.csv`` and
``sweep.json``::

    DIR/
        dx=0.02,mode=original/      a normal run folder (summary.json, frames/, ...)
        dx=0.02,mode=adaptive/
        ...
        sweep.csv                   one row per run: values, status, headline figures
        sweep.json                  the same rows, with the sweep's definition

A value is parsed as a TOML value (``0.02``, ``1e-3``, ``true``, ``"text"``,
``[0, 1, 0]``); anything TOML does not parse is a bare string (``adaptive``).
Every combination is applied to the scene and validated with the scene model before
anything runs, so a misspelt key or a refused value is one error naming the key.

The runs go one after another in this process, or (``ray=...``) as Ray tasks that
write into the same folder: on a cluster of several machines, ``DIR`` must be on a
filesystem every node sees. A run that blows up or fails is recorded in its row and
the sweep goes on.
"""

from __future__ import annotations

import contextlib
import copy
import csv
import hashlib
import itertools
import math
import os
import re
import time
import tomllib
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from abmpm.errors import AbmpmError, SceneError, SimulationBlowUp

__all__ = [
    "SceneSource",
    "SweepPlan",
    "parse_set",
    "parse_values",
    "parse_key",
    "apply_overrides",
    "plan_sweep",
    "feasible_on",
    "run_one",
    "run_sweep",
    "write_results",
    "CSV_FILE",
    "JSON_FILE",
    "RAY_MISSING",
]

CSV_FILE = "sweep.csv"
JSON_FILE = "sweep.json"
RAY_MISSING = "--ray needs ray: pip install 'abmpm[sweep]'"

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


# --------------------------------------------------------------------------- parsing


_SEGMENT = re.compile(r"([A-Za-z_][A-Za-z0-9_-]*)((?:\[\d+\])*)$")


def parse_key(key: str) -> list[str | int]:
    """``"materials[0].bulk_modulus"`` -> ``["materials", 0, "bulk_modulus"]``
    (``materials.0.bulk_modulus`` too)."""
    text = key.strip()
    if not text:
        raise AbmpmError("--set: empty key (expected KEY=V1,V2,..., e.g. simulation.dx=0.02,0.01)")
    out: list[str | int] = []
    for part in text.split("."):
        if part.isdigit() and out:
            out.append(int(part))
            continue
        m = _SEGMENT.match(part)
        if not m:
            raise AbmpmError(
                f"--set {text}: not a key path (expected dotted names such as "
                f"simulation.refinement.mode or materials[0].density)"
            )
        out.append(m.group(1))
        out += [int(i) for i in re.findall(r"\[(\d+)\]", m.group(2))]
    return out


def key_text(path: Sequence[str | int]) -> str:
    """The canonical spelling of a key path: ``materials[0].density``."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else ("." if out else "") + p
    return out


def _split_top(text: str) -> list[str]:
    """Split at the commas that are not inside quotes, [...] or {...}."""
    items, cur, depth, quote = [], [], 0, ""
    i = 0
    while i < len(text):
        c = text[i]
        if quote:
            cur.append(c)
            if c == "\\" and quote == '"' and i + 1 < len(text):
                cur.append(text[i + 1])
                i += 1
            elif c == quote:
                quote = ""
        elif c in "\"'":
            quote = c
            cur.append(c)
        elif c in "[{":
            depth += 1
            cur.append(c)
        elif c in "]}":
            depth -= 1
            cur.append(c)
        elif c == "," and depth <= 0:
            items.append("".join(cur))
            cur = []
        else:
            cur.append(c)
        i += 1
    items.append("".join(cur))
    return items


def _parse_value(token: str) -> Any:
    """A TOML value (number, boolean, quoted string, array, inline table), else the
    text itself as a string."""
    try:
        return tomllib.loads(f"v = {token}")["v"]
    except tomllib.TOMLDecodeError:
        return token


def parse_values(key: str, text: str) -> list[Any]:
    """``"0.02,0.01"`` -> ``[0.02, 0.01]``; an empty list, an empty item or a value
    given twice is an error naming the key."""
    if not text.strip():
        raise AbmpmError(f"--set {key}: no values given (expected {key}=V1,V2,...)")
    values: list[Any] = []
    for n, token in enumerate(_split_top(text), 1):
        token = token.strip()
        if not token:
            raise AbmpmError(f"--set {key}: value {n} is empty (in {text!r})")
        value = _parse_value(token)
        if any(type(v) is type(value) and v == value for v in values):
            raise AbmpmError(f"--set {key}: value {token} is given twice")
        values.append(value)
    return values


def parse_set(items: Iterable[str]) -> dict[str, list[Any]]:
    """``["simulation.dx=0.02,0.01", ...]`` -> ``{"simulation.dx": [0.02, 0.01], ...}``
    (keys in their canonical spelling, in the order given)."""
    out: dict[str, list[Any]] = {}
    for item in items:
        key, eq, text = str(item).partition("=")
        if not eq:
            raise AbmpmError(f"--set {item}: expected KEY=V1,V2,... (e.g. simulation.dx=0.02,0.01)")
        canon = key_text(parse_key(key))
        if canon in out:
            raise AbmpmError(f"--set {canon}: given twice; list all its values in one --set")
        out[canon] = parse_values(canon, text)
    if not out:
        raise AbmpmError("nothing to sweep: give at least one --set KEY=V1,V2,...")
    return out


def format_value(value: Any) -> str:
    """A value as it would be written on the command line (TOML for non-strings)."""
    if isinstance(value, str):
        return value
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(format_value(v) if not isinstance(v, str) else repr(v) for v in value) + "]"
    return str(value)


# --------------------------------------------------------------------------- scenes


@dataclass
class SceneSource:
    """A scene as its plain TOML document, with what the loader needs to validate it
    (label for errors, folder of relative mesh paths, default name). Picklable: this
    is what a Ray task receives."""

    data: dict
    label: str = "scene"
    base_dir: str | None = None
    default_name: str | None = None

    def build(self, overrides: Mapping[str, Any] | None = None, label: str | None = None):
        """The validated Scene with ``overrides`` ({key: value}) applied."""
        from abmpm.scene.loader import scene_from_dict

        data = apply_overrides(self.data, overrides or {})
        return scene_from_dict(data, label=label or self.label, base_dir=self.base_dir,
                               default_name=self.default_name)


def scene_source(scene) -> SceneSource:
    """A SceneSource from a SceneSource, a Scene, a plain dict, a ``.toml`` path or a
    built-in name (the file is validated as it is first: its own errors come first)."""
    from abmpm.scene.loader import builtin_scene_path, load_scene
    from abmpm.scene.model import Scene

    if isinstance(scene, SceneSource):
        return scene
    if isinstance(scene, Scene):
        base = str(scene.base_dir) if scene.base_dir is not None else None
        return SceneSource(scene.model_dump(mode="json"), label=scene.name, base_dir=base)
    if isinstance(scene, Mapping):
        return SceneSource(copy.deepcopy(dict(scene)), label=str(scene.get("name", "scene")))
    text = os.fspath(scene)
    load_scene(text)  # SceneError for a missing file, bad TOML or bad contents
    path = Path(text).expanduser()
    label = text
    if not path.is_file():
        path, label = builtin_scene_path(text), f"{text} (built-in)"
    with open(path, "rb") as f:
        data = tomllib.load(f)
    return SceneSource(data, label=label, base_dir=str(path.parent.resolve()), default_name=path.stem)


def _kind(value: Any) -> str:
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return "a number"
    return "a string" if isinstance(value, str) else type(value).__name__


def apply_overrides(data: Mapping, overrides: Mapping[str, Any]) -> dict:
    """A deep copy of the scene document ``data`` with each ``key: value`` set; missing
    tables on the way are created (the scene model then refuses unknown keys)."""
    out = copy.deepcopy(dict(data))
    for key, value in overrides.items():
        path = parse_key(key) if isinstance(key, str) else list(key)
        name = key_text(path)
        node: Any = out
        for i, part in enumerate(path):
            here = key_text(path[:i]) or "the scene"
            last = i == len(path) - 1
            if isinstance(part, int):
                if not isinstance(node, list):
                    raise SceneError(f"--set {name}: {here} is {_kind(node)}, not a list; drop [{part}]")
                if part >= len(node):
                    raise SceneError(
                        f"--set {name}: {here} has {len(node)} entr{'y' if len(node) == 1 else 'ies'} "
                        f"(index 0 to {len(node) - 1})"
                    )
            else:
                if isinstance(node, list):
                    raise SceneError(
                        f"--set {name}: {here} is a list; give the index of an entry, "
                        f"e.g. {key_text(path[:i] + [0] + path[i:])}"
                    )
                if not isinstance(node, dict):
                    raise SceneError(f"--set {name}: {here} is {_kind(node)}, not a table")
            if last:
                node[part] = copy.deepcopy(value)
            else:
                if isinstance(part, str) and node.get(part) is None:
                    node[part] = {}
                node = node[part]
    return out


# --------------------------------------------------------------------------- planning


_UNSAFE = re.compile(r"[^A-Za-z0-9._=,+-]+")
_MAX_NAME = 120


def _short_keys(keys: Sequence[str]) -> dict[str, str]:
    """The shortest unique tail of each key path: simulation.dx -> dx; two
    ``density`` keys: materials.0.density, materials.1.density (an index is never
    shown without the name of its list)."""
    parts = {k: parse_key(k) for k in keys}

    def grow(k: str, d: int) -> int:
        d = min(d, len(parts[k]))
        while d < len(parts[k]) and isinstance(parts[k][-d], int):
            d += 1
        return d

    depth = {k: grow(k, 1) for k in keys}
    while True:
        names = {k: ".".join(str(p) for p in parts[k][-depth[k]:]) for k in keys}
        clash = [k for k in keys if list(names.values()).count(names[k]) > 1 and depth[k] < len(parts[k])]
        if not clash:
            return names
        for k in clash:
            depth[k] = grow(k, depth[k] + 1)


def _folder_value(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "_".join(_folder_value(v) for v in value)
    return format_value(value)


def folder_name(overrides: Mapping[str, Any], short: Mapping[str, str]) -> str:
    """``{"simulation.dx": 0.02, "simulation.refinement.mode": "original"}`` ->
    ``dx=0.02,mode=original`` (characters a file system may refuse become ``_``)."""
    name = ",".join(f"{short[k]}={_folder_value(v)}" for k, v in overrides.items())
    name = _UNSAFE.sub("_", name).strip(". ") or "run"
    if len(name) > _MAX_NAME:
        digest = hashlib.sha1(name.encode()).hexdigest()[:8]
        name = name[: _MAX_NAME - 9] + "~" + digest
    return name


@dataclass
class SweepPlan:
    """The validated combinations of a sweep: ``runs`` is a list of (folder name,
    {key: value}) in the order of the Cartesian product (last key fastest)."""

    source: SceneSource
    values: dict[str, list[Any]]
    runs: list[tuple[str, dict[str, Any]]]


def plan_sweep(scene, values: Mapping[str, Sequence[Any]], check: Callable | None = None) -> SweepPlan:
    """Validate every value and every combination against the scene model (SceneError
    naming the key and the value) and name their folders. ``check(scene, overrides)``,
    if given, is called on each validated combination (e.g. the feasibility check)."""
    source = scene_source(scene)
    if not values:
        raise AbmpmError("nothing to sweep: give at least one --set KEY=V1,V2,...")
    values = {key_text(parse_key(k)) if isinstance(k, str) else key_text(k): list(v) for k, v in values.items()}
    for key, vals in values.items():
        if not vals:
            raise AbmpmError(f"--set {key}: no values given (expected {key}=V1,V2,...)")
    # one key at a time first: the error names the --set that is wrong
    for key, vals in values.items():
        for v in vals:
            source.build({key: v}, label=f"--set {key}={format_value(v)}")
    combos = [dict(zip(values, c)) for c in itertools.product(*values.values())]
    for combo in combos:
        label = " ".join(f"--set {k}={format_value(v)}" for k, v in combo.items())
        sc = source.build(combo, label=label) if len(combo) > 1 else source.build(combo)
        if check is not None:
            try:
                check(sc, combo)
            except SceneError as exc:
                raise SceneError(f"{label}: {exc}") from None
    short = _short_keys(list(values))
    runs, seen = [], set()
    for combo in combos:
        name = base = folder_name(combo, short)
        n = 2
        while name.lower() in seen:  # case-insensitive file systems, '_' substitutions
            name, n = f"{base}~{n}", n + 1
        seen.add(name.lower())
        runs.append((name, combo))
    return SweepPlan(source, values, runs)


# --------------------------------------------------------------------------- one run


def feasible_on(device: str | None) -> Callable:
    """A ``check`` for :func:`plan_sweep`: each combination must fit in this machine's
    memory and be time-steppable (:meth:`Scene.check_feasible`), before any run starts.
    (On Ray each run checks itself on the node it lands on.)"""

    def check(scene, overrides) -> None:
        scene.check_feasible(None, device)

    return check


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
    import json

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
    ``run``, the set values, ``status`` (completed, blew_up or error), ``message`` and
    the headline figures of its summary. A blow-up or an error is recorded, not raised
    (KeyboardInterrupt is)."""
    from abmpm.runner import run

    out = Path(out)
    row: dict[str, Any] = {"run": name or out.name, **dict(overrides), "status": "error", "message": None}
    summary = None
    try:
        sc = scene_source(scene).build(overrides)
        with _threads_env(threads):
            summary = run(sc, out, device=device, frames=frames, preview=preview, progress=False)
        row["status"] = summary.get("status", "completed")
        row["message"] = summary.get("message")
    except SimulationBlowUp as exc:
        summary = _read_summary(out)
        row["status"], row["message"] = "blew_up", str(exc)
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


def _ray_run_one(*args, **kwargs) -> dict[str, Any]:
    """run_one in a Ray worker: Warp quiet, as under the CLI."""
    from abmpm.cli import _quiet_warp

    _quiet_warp()
    return run_one(*args, **kwargs)


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
    from abmpm.io.atomic import atomic_write
    from abmpm.io.summary import write_json

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


def _ray_device(ray, device: str | None, scene) -> tuple[str, int]:
    """(device for the task, GPUs it asks for). Ray hands a task its GPU as cuda:0
    (CUDA_VISIBLE_DEVICES); no device: cuda when the cluster has a GPU."""
    want = device if device is not None else scene.simulation.device
    if want in (None, "", "auto"):
        want = "cuda" if ray.cluster_resources().get("GPU", 0) >= 1 else "cpu"
    return ("cuda", 1) if str(want).startswith("cuda") else (str(want), 0)


def import_ray():
    """The ray module, or AbmpmError telling how to install it."""
    try:
        import ray
    except ImportError:
        raise AbmpmError(RAY_MISSING) from None
    return ray


_NO_CLUSTER = "is a cluster running there? (start one with `ray start --head`)"
_AUTH_HINT = f"{_NO_CLUSTER}; a cluster with token authentication also needs RAY_AUTH_MODE=token here"


def _reachable(address: str, timeout: float = 5.0) -> bool | None:
    """Whether something listens at ``host:port`` (``ray://host:port`` too); None when
    the address is not of that form. Ray itself retries an unreachable address for
    many minutes."""
    import socket

    text = address.split("://", 1)[-1].rstrip("/")
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not host:
        return None
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            return True
    except OSError:
        return False


def _latest_local_cluster() -> str | None:
    """The address of the cluster last started with ``ray start`` on this machine
    (Ray's own record, which outlives a cluster that was killed), or None."""
    try:
        from ray._private.utils import read_ray_address

        return read_ray_address() or None
    except Exception:  # a Ray version without it: let ray.init() decide
        return None


def _init_ray(ray, address: str) -> bool:
    """Connect (or start) Ray unless this process already is; True if we did.

    ``auto``: the cluster in $RAY_ADDRESS, else the latest one started on this machine
    with ``ray start`` if it is still running, else a new local instance. (That is
    ``ray.init()``, which, unlike us, waits for minutes on a cluster that was killed;
    ``ray.init(address="auto")`` raises ConnectionError when there is no cluster.)
    ``local``: always a new local instance. Anything else is a cluster address
    (``host:6379``, ``ray://host:10001``).
    """
    import logging

    if ray.is_initialized():
        return False
    addr: str | None = address
    if address == "auto":
        addr = None
        env = os.environ.get("RAY_ADDRESS")
        if env:
            if _reachable(env) is False:
                raise AbmpmError(f"--ray auto: no Ray cluster answers at $RAY_ADDRESS={env}; {_NO_CLUSTER}")
        else:
            latest = _latest_local_cluster()
            if latest and _reachable(latest) is False:
                addr = "local"  # that cluster is gone: start a local instance
    elif address != "local" and _reachable(address) is False:
        raise AbmpmError(f"--ray {address}: no Ray cluster answers at {address}; {_NO_CLUSTER}")
    try:
        ray.init(address=addr, logging_level=logging.WARNING, log_to_driver=True)
    except (ConnectionError, ValueError, RuntimeError) as exc:
        msg = " ".join(str(exc).split())
        raise AbmpmError(f"--ray {address}: cannot connect to Ray: {msg}; {_AUTH_HINT}") from None
    return True


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
    from abmpm.io.outdir import prepare_out_dir

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
        _sweep_on_ray(ray_mod, plan, out, frames, device, threads, preview, on_start, done)
    final = [r for r in rows if r is not None]
    meta["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    write_results(out, final, meta)
    return final


def _sweep_on_ray(ray, plan, out, frames, device, threads, preview, on_start, done) -> None:
    """Submit every combination as a Ray task; hand each row to ``done`` as it comes."""
    remote = ray.remote(_ray_run_one)
    pending: dict[Any, int] = {}
    n = len(plan.runs)
    for i, (name, combo) in enumerate(plan.runs):
        dev, gpus = _ray_device(ray, device, plan.source.build(combo))
        cpus = 1 if gpus else (threads or 1)
        ref = remote.options(num_cpus=cpus, num_gpus=gpus, name=f"abmpm-sweep:{name}", max_retries=0).remote(
            plan.source, combo, str(out / name), frames=frames, device=dev,
            threads=None if gpus else cpus, preview=preview, name=name,
        )
        pending[ref] = i
        if on_start:
            on_start(i + 1, n, name)
    try:
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            ref = ready[0]
            i = pending.pop(ref)
            name, combo = plan.runs[i]
            try:
                row = ray.get(ref)
            except Exception as exc:  # the task died (worker crash, lost node, ...)
                msg = " ".join(str(exc).split())
                row = {"run": name, **combo, "status": "error",
                       "message": f"Ray task failed: {type(exc).__name__}: {msg[:500]}"}
            done(i, row)
    except BaseException:  # Ctrl-C: do not leave the other runs going
        for ref in pending:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)
        raise
