"""Loading scenes from TOML files, from a run's record (``scene.json``) and from the
built-in scene library.

``load_scene("my_scene.toml")`` or ``load_scene("dam_break")`` returns a validated
:class:`~abmpm.scene.model.Scene`. Everything a user can get wrong in a scene file
becomes one :class:`~abmpm.errors.SceneError` whose message has one line per
problem, ``"{file}: {dotted.key.path}: {message}"``, e.g.::

    scene.toml: materials[1].youngs_modulus: must be > 0
    scene.toml: simulation.dxx: unknown key

Relative mesh paths in the file resolve against the file's folder
(``scene.base_dir``); a scene without a ``name`` is named after the file's stem.
"""

from __future__ import annotations

import json
import os
import re
import tomllib
import typing
from importlib import resources
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from abmpm.errors import SceneError
from abmpm.scene import model as sm

RECORD_BASE_DIR = "base_dir"  # the key of a run's scene.json that holds its scene file's folder

__all__ = ["load_scene", "read_scene_document", "scene_record", "list_builtin_scenes", "builtin_scene_path",
           "format_validation_error"]

_BUILTIN_PACKAGE = "abmpm.scene"
_BUILTIN_FOLDER = "builtin"


def _tags(union) -> list[str]:
    """The discriminator values (``model`` / ``shape``) of a discriminated union."""
    members = typing.get_args(typing.get_args(union)[0])
    out = []
    for cls in members:
        for name in ("model", "shape"):
            if name in cls.model_fields:
                out.append(cls.model_fields[name].default)
    return out


MATERIAL_MODELS = _tags(sm.Material)
BODY_SHAPES = _tags(sm.Body)
COLLIDER_SHAPES = _tags(sm.Collider)
_TAGS = set(MATERIAL_MODELS) | set(BODY_SHAPES) | set(COLLIDER_SHAPES)
# pydantic labels union members in the location of an error ('float', 'tuple[...]')
_UNION_LABELS = {"float", "int", "str", "bool", "none", "list", "dict", "tuple"}


# --------------------------------------------------------------------------- built-ins


def _builtin_dir():
    return resources.files(_BUILTIN_PACKAGE).joinpath(_BUILTIN_FOLDER)


def _builtin_names() -> list[str]:
    folder = _builtin_dir()
    try:
        entries = list(folder.iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return []
    return sorted(e.name[: -len(".toml")] for e in entries if e.name.endswith(".toml"))


def builtin_scene_path(name: str) -> Path:
    """File of the built-in scene ``name`` (SceneError listing the built-ins if unknown)."""
    names = _builtin_names()
    if name not in names:
        raise SceneError(
            f"unknown scene {name!r}: no such file and not a built-in scene "
            f"(built-ins: {', '.join(names) or 'none'})"
        )
    return Path(str(_builtin_dir().joinpath(name + ".toml")))


def list_builtin_scenes() -> dict[str, str]:
    """``{name: description}`` of the scenes shipped with abmpm, sorted by name."""
    out = {}
    for name in _builtin_names():
        path = builtin_scene_path(name)
        try:
            with open(path, "rb") as f:
                data = tomllib.load(f)
            out[name] = str(data.get("description", ""))
        except (OSError, tomllib.TOMLDecodeError):
            out[name] = ""
    return out


# --------------------------------------------------------------------------- loading


def load_scene(path_or_name: str | os.PathLike) -> sm.Scene:
    """Load a scene from a ``.toml`` file, a run's ``scene.json`` or by built-in name (``"dam_break"``).

    Raises :class:`SceneError` for a missing or unreadable file, a TOML syntax error,
    an unknown built-in name, or invalid contents (one line per problem).
    """
    if isinstance(path_or_name, sm.Scene):
        return path_or_name
    data, label, path, base_dir = read_scene_document(path_or_name)
    return scene_from_dict(data, label=label, base_dir=base_dir, default_name=path.stem)


def read_scene_document(path_or_name: str | os.PathLike) -> tuple[dict[str, Any], str, Path, Path]:
    """The parsed TOML of a scene file or a built-in scene (or the JSON of a run's
    ``scene.json``), not yet validated: ``(document, label for errors, path of the file,
    folder its relative file paths resolve against)``. SceneError for a missing or
    unreadable file, a syntax error or an unknown built-in name."""
    if not isinstance(path_or_name, (str, os.PathLike)):
        raise SceneError(f"expected a scene file or a built-in name, got {path_or_name!r}")
    text = os.fspath(path_or_name)
    if not text.strip():
        raise SceneError("the scene's file or built-in name is empty")
    path = Path(text).expanduser()
    label = text
    try:
        is_file = path.is_file()
    except OSError as exc:  # a name too long for the file system, ...
        raise SceneError(f"{text[:60]}{'...' if len(text) > 60 else ''}: {exc.strerror or exc}") from None
    if not is_file:
        looks_like_name = path.suffix == "" and not (os.sep in text or (os.altsep and os.altsep in text))
        if path.exists() and not (looks_like_name and text in list_builtin_scenes()):
            raise SceneError(f"{text}: is not a file")
        # a built-in name: also when a folder of that name is here (a run's output, `--out NAME`)
        looks_like_path = path.suffix.lower() == ".toml" or os.sep in text or (os.altsep and os.altsep in text)
        if looks_like_path:
            raise SceneError(f"{text}: scene file not found")
        path, label = builtin_scene_path(text), f"{text} (built-in)"
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SceneError(f"{label}: cannot read file ({exc.strerror or exc})") from exc
    # a run's own record of its scene (scene.json in its folder) runs as well
    kind = "JSON" if path.suffix.lower() == ".json" else "TOML"
    try:
        text = raw.decode("utf-8")
        data = json.loads(text) if kind == "JSON" else tomllib.loads(text)
    except UnicodeDecodeError as exc:
        raise SceneError(f"{label}: {kind} syntax error: file is not UTF-8 text ({exc.reason})") from exc
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise SceneError(f"{label}: {kind} syntax error: {exc}") from exc
    if not isinstance(data, dict):
        raise SceneError(f"{label}: a scene is a table of settings, not a {type(data).__name__}")
    base_dir = path.parent
    if kind == "JSON" and isinstance(data.get(RECORD_BASE_DIR), str):  # where the run's scene file was
        base_dir = Path(data.pop(RECORD_BASE_DIR))
    return data, label, path, base_dir.resolve()


def scene_record(scene: sm.Scene) -> dict[str, Any]:
    """The scene as a run records it (``scene.json``): its validated settings and the
    folder its relative file paths resolve against, so that the record runs as the file did."""
    data = scene.model_dump(mode="json")
    if scene.base_dir is not None:
        data[RECORD_BASE_DIR] = str(scene.base_dir)
    return data


def scene_from_dict(
    data: dict[str, Any],
    label: str = "scene",
    base_dir: str | os.PathLike | None = None,
    default_name: str | None = None,
) -> sm.Scene:
    """Validate a parsed TOML document (plain dict) into a Scene, with friendly errors."""
    data = dict(data)
    if "base_dir" in data:  # set by the loader, not a user key
        raise SceneError(f"{label}: base_dir: unknown key")
    if default_name and "name" not in data:
        data["name"] = default_name
    try:
        scene = sm.Scene.model_validate(data)
    except ValidationError as exc:
        raise SceneError(format_validation_error(exc, label)) from None
    if base_dir is not None:
        scene.base_dir = Path(base_dir).resolve()
    return scene


# --------------------------------------------------------------------------- error text


def _dotted(loc: tuple) -> str:
    """('materials', 1, 'elastic', 'youngs_modulus') -> 'materials[1].youngs_modulus'."""
    out = ""
    prev_int = False
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
            prev_int = True
            continue
        s = str(part)
        if prev_int and s in _TAGS:  # discriminated-union tag
            prev_int = False
            continue
        prev_int = False
        if s in _UNION_LABELS or "[" in s or s.startswith("function-"):
            continue
        out += ("." if out else "") + s
    return out


def _got(value: Any) -> str:
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return repr(value) if len(value) <= 40 else repr(value[:37] + "...")
    return repr(value)


def _choices(expected: str) -> str:
    """"'a', 'b' or 'c'" -> 'a, b, c'."""
    return ", ".join(re.findall(r"'([^']*)'", expected))


_EXPECTED = {
    "float_type": "a number",
    "float_parsing": "a number",
    "int_type": "an integer",
    "int_parsing": "an integer",
    "int_from_float": "an integer",
    "bool_type": "true or false",
    "bool_parsing": "true or false",
    "string_type": "a string",
    "list_type": "a list",
    "tuple_type": "a list of 3 numbers",
    "model_type": "a table",
    "model_attributes_type": "a table",
    "dict_type": "a table",
    "path_type": "a file path (string)",
    "finite_number": "a finite number",
}

_COMPARE = {
    "greater_than": (">", "gt"),
    "greater_than_equal": (">=", "ge"),
    "less_than": ("<", "lt"),
    "less_than_equal": ("<=", "le"),
}


def _fmt_num(x) -> str:
    if isinstance(x, float) and x.is_integer():
        return str(int(x))
    return str(x)


def _message(err: dict) -> tuple[str, str]:
    """(dotted key path, short plain message) for one pydantic error."""
    typ = err["type"]
    loc = tuple(err["loc"])
    ctx = err.get("ctx") or {}
    value = err.get("input")
    path = _dotted(loc)
    if len(loc) >= 2 and loc[-2] == "boxes" and isinstance(loc[-1], int) and typ != "value_error":
        # a box of the wrong shape: its two corners, not a vector
        got = f"a list of {len(value)}" if isinstance(value, (list, tuple)) else _got(value)
        return path, f"expected a box [[min x, y, z], [max x, y, z]] (two corners), got {got}"
    if typ == "extra_forbidden":
        return path, "unknown key"
    if typ == "missing":
        if loc and isinstance(loc[-1], int):  # a short vector: [1, 2] for (x, y, z)
            n = len(value) if isinstance(value, (list, tuple)) else 0
            return _dotted(loc[:-1]), f"expected a list of 3 numbers [x, y, z], got {n}"
        return path, "required key missing"
    if typ in ("union_tag_invalid", "union_tag_not_found"):
        disc = ctx.get("discriminator", "").strip("'") or "model"
        if disc == "model":
            choices = ", ".join(MATERIAL_MODELS)
        elif loc and loc[0] == "colliders":
            choices = ", ".join(COLLIDER_SHAPES)
        else:
            choices = ", ".join(BODY_SHAPES)
        if typ == "union_tag_not_found":
            if not isinstance(value, dict):
                return path, f"expected a table, got {_got(value)}"
            return _dotted(loc + (disc,)), f"required key missing (choose from {choices})"
        return _dotted(loc + (disc,)), f'unknown {disc} "{ctx.get("tag")}" (choose from {choices})'
    if typ in _COMPARE:
        op, key = _COMPARE[typ]
        return path, f"must be {op} {_fmt_num(ctx.get(key))}"
    if typ == "literal_error":
        return path, f"must be one of {_choices(ctx.get('expected', ''))}, got {_got(value)}"
    if typ == "too_short":
        if ctx.get("field_type") == "Tuple":
            return path, f"expected a list of 3 numbers [x, y, z], got {ctx.get('actual_length')}"
        n = ctx.get("min_length", 1)
        return path, f"needs at least {n} entr{'y' if n == 1 else 'ies'}"
    if typ == "too_long":
        if ctx.get("field_type") == "Tuple":
            return path, f"expected a list of 3 numbers [x, y, z], got {ctx.get('actual_length')}"
        return path, f"at most {ctx.get('max_length')} entries allowed"
    if typ == "string_too_short":
        return path, "must not be empty"
    if typ in _EXPECTED:
        return path, f"expected {_EXPECTED[typ]}, got {_got(value)}"
    if typ in ("value_error", "assertion_error"):
        msg = str(ctx.get("error", err["msg"]))
        msg = re.sub(r"^(Value error|Assertion failed), ", "", msg)
        # model-level checks name their own field: "bodies[0].material: unknown ..."
        m = re.match(r"^([A-Za-z_][\w.\[\]]*): (.*)$", msg, re.S)
        if m and ("[" in m.group(1) or "." in m.group(1)):
            return ".".join(p for p in (path, m.group(1)) if p), m.group(2)
        # SimulationSettings' box check is about a named field
        for field in ("dx", "domain_max", "domain_min"):
            if path == "simulation" and msg.startswith(field):
                return f"simulation.{field}", msg
        return path, msg
    return path, err["msg"]


def format_validation_error(exc: ValidationError, label: str) -> str:
    """One line per problem: ``"{label}: {dotted.key}: {message}"`` (union duplicates merged)."""
    merged: dict[str, list[str]] = {}
    for err in exc.errors(include_url=False):
        path, msg = _message(err)
        merged.setdefault(path, [])
        if msg not in merged[path]:
            merged[path].append(msg)
    # A union (scale: a number or [x, y, z]) reports a type mismatch for one member
    # and the real problem inside the other (scale[1]: ...): keep the specific one.
    for path in list(merged):
        if path and any(p.startswith((path + "[", path + ".")) for p in merged):
            merged[path] = [m for m in merged[path] if not m.startswith("expected ")]
            if not merged[path]:
                del merged[path]
    lines = []
    for path, msgs in merged.items():
        expected = [m for m in msgs if m.startswith("expected ")]
        if len(expected) > 1:  # e.g. scale: a number or a list of 3 numbers
            got = ""
            whats = []
            for m in expected:
                what, _, g = m[len("expected "):].partition(", got ")
                whats.append(what)
                got = got or g
            msgs = [m for m in msgs if m not in expected]
            msgs.insert(0, f"expected {' or '.join(whats)}" + (f", got {got}" if got else ""))
        for m in msgs:
            lines.append(f"{label}: {path}: {m}" if path else f"{label}: {m}")
    return "\n".join(lines)
