"""Planning a sweep: ``--set`` keys and values, a scene with overrides applied,
validation of every combination, folder names (:class:`SweepPlan`,
:func:`plan_sweep`) and the up-front feasibility check (:func:`feasible_on`)."""

from __future__ import annotations

import copy
import hashlib
import itertools
import math
import re
import tomllib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from abmpm.errors import AbmpmError, SceneError
from abmpm.scene.loader import read_scene_document, scene_from_dict
from abmpm.scene.model import Scene

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
        data = apply_overrides(self.data, overrides or {})
        return scene_from_dict(data, label=label or self.label, base_dir=self.base_dir,
                               default_name=self.default_name)


def scene_source(scene) -> SceneSource:
    """A SceneSource from a SceneSource, a Scene, a plain dict, a ``.toml`` path or a
    built-in name (the file is validated as it is first: its own errors come first)."""
    if isinstance(scene, SceneSource):
        return scene
    if isinstance(scene, Scene):
        base = str(scene.base_dir) if scene.base_dir is not None else None
        return SceneSource(scene.model_dump(mode="json"), label=scene.name, base_dir=base)
    if isinstance(scene, Mapping):
        return SceneSource(copy.deepcopy(dict(scene)), label=str(scene.get("name", "scene")))
    data, label, path, base_dir = read_scene_document(scene)  # SceneError for a missing file or bad TOML
    source = SceneSource(data, label=label, base_dir=str(base_dir), default_name=path.stem)
    source.build()  # the file is validated as it is first: its own errors come first
    return source


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


def feasible_on(device: str | None) -> Callable:
    """A ``check`` for :func:`plan_sweep`: each combination must fit in this machine's
    memory and be time-steppable (:meth:`Scene.check_feasible`), before any run starts.
    (On Ray each run checks itself on the node it lands on.)"""

    def check(scene, overrides) -> None:
        scene.check_feasible(None, device)

    return check
