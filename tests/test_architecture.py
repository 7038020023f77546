"""The house rules of the code base, checked (docs/architecture.md):

* the import contracts of pyproject.toml (``[tool.importlinter]``): ``sim/`` imports
  nothing above it, and the layers scene -> geometry -> solver inputs -> step ->
  writers -> commands, checked by import-linter;
* no import cycle between modules, function-local imports and the package
  ``__init__`` an import runs included (grimp);
* function-local imports only for optional dependencies;
* no source file over 500 lines;
* every file (and ``file`` (``name``) / ``file::name``) the docs point to exists.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import grimp
import pytest
from importlinter.cli import lint_imports

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "abmpm"
MAX_LINES = 500
# the extras (pyproject.toml) and what only some machines have: imported where used
OPTIONAL = {"pxr", "pysplashsurf", "ray", "viser", "numba", "mitsuba", "drjit", "bpy", "mathutils"}


def _sources() -> list[Path]:
    return sorted(SRC.rglob("*.py"))


def test_import_contracts_are_kept(monkeypatch):
    """sim/ imports nothing of abmpm outside it; every module imports only from its
    layer or the ones below (the list in pyproject.toml)."""
    monkeypatch.chdir(ROOT)  # where lint-imports finds pyproject.toml
    assert lint_imports(no_cache=True) == 0, "an import contract is broken: run `lint-imports` for the chain"


def _ancestors(module: str) -> list[str]:
    parts = module.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def import_edges(graph) -> dict[str, set[str]]:
    """Direct imports, plus what importing a module runs first: the ``__init__`` of
    each package above it (except the importer's own packages, initialised already)."""
    edges = {}
    for importer in graph.modules:
        out = set()
        for imported in graph.find_modules_directly_imported_by(importer):
            out |= {imported, *_ancestors(imported)} - {importer, *_ancestors(importer)}
        edges[importer] = out
    return edges


def strongly_connected(edges: dict[str, set[str]]) -> list[list[str]]:
    """The groups of modules that import each other, directly or not (Tarjan)."""
    index, low, stack, on, groups = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return groups


def test_no_import_cycles():
    """No module is reached again from what it imports, counting imports inside
    functions (a cycle held up by function-local imports is still a cycle) and the
    package ``__init__`` an import runs first (a writer imported from a module that
    the writers' package imports is a cycle)."""
    groups = strongly_connected(import_edges(grimp.build_graph("abmpm", cache_dir=None)))
    assert not groups, "modules importing each other:\n" + "\n".join(" <-> ".join(g) for g in groups)


def test_the_cycle_check_can_fail():
    edges = {"a.x": {"a.y.z"}, "a.y": {"a.y.w"}, "a.y.w": {"a.x"}, "a.y.z": set()}
    assert strongly_connected(edges) == []  # no package __init__ counted yet
    implicit = {k: v | {p for m in v for p in _ancestors(m)} - {k, *_ancestors(k)} for k, v in edges.items()}
    assert strongly_connected(implicit) == [["a.x", "a.y", "a.y.w"]]


def _local_imports(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text())
    found = []
    for func in ast.walk(tree):
        if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(func):
            if isinstance(node, ast.Import):
                found += [(node.lineno, a.name) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                found.append((node.lineno, "." * node.level + (node.module or "")))
    return found


def test_function_local_imports_only_for_optional_dependencies():
    bad = [f"{p.relative_to(ROOT)}:{line} imports {mod}" for p in _sources() for line, mod in _local_imports(p)
           if mod.split(".")[0] not in OPTIONAL]
    assert not bad, "import these at the top of the module:\n" + "\n".join(bad)


def test_the_local_import_check_can_fail(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("def f():\n    import numpy\n    from . import x\n")
    assert _local_imports(p) == [(2, "numpy"), (3, ".")]


def test_no_source_file_is_over_500_lines():
    long = {str(p.relative_to(ROOT)): n for p in _sources() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"split these (over {MAX_LINES} lines): {long}"


# `sim/colliders.py`, `sim/p2g.py` (`p2g_overlap`), `tests/test_adaptive.py::test_x`, `sim/g2p.py:advect`
DOC_REFERENCE = re.compile(r"`([\w./-]+\.py)(?:(?::{1,2})([\w.]+))?`(?: \(`([\w.]+)`\))?")


def _resolve(ref: str) -> list[Path]:
    # relative to the repository, to src/abmpm, or a bare file name anywhere in
    # src/abmpm or tests/
    for base in (ROOT, SRC, SRC.parent):
        if (base / ref).is_file():
            return [base / ref]
    return sorted(SRC.rglob(ref)) + sorted((ROOT / "tests").glob(ref)) if "/" not in ref else []


def _defines(path: Path, name: str) -> bool:
    tree = ast.parse(path.read_text())
    head = name.split(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name == head:
            return True
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == head for t in node.targets):
            return True
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.target.id == head:
            return True
    return False


def _doc_references(text: str):
    for m in DOC_REFERENCE.finditer(text):
        ref, name = m.group(1), m.group(2) or m.group(3)
        if ref.startswith("shared/"):  # the team's shared folder, not part of this repository
            continue
        yield ref, name


def _broken(text: str) -> list[str]:
    bad = []
    for ref, name in _doc_references(text):
        files = _resolve(ref)
        if not files:
            bad.append(f"{ref}: no such file")
        elif name and not any(_defines(f, name) for f in files):
            bad.append(f"{ref}: defines no {name}")
    return bad


@pytest.mark.parametrize("doc", sorted(p.name for p in (ROOT / "docs").glob("*.md")) + ["README.md"])
def test_every_file_and_function_the_docs_name_exists(doc):
    path = ROOT / doc if doc == "README.md" else ROOT / "docs" / doc
    bad = _broken(path.read_text())
    assert not bad, f"{doc} points to what is not there:\n" + "\n".join(bad)


def test_the_docs_reference_check_can_fail():
    assert _broken("see `sim/p2g.py` (`p2g_overlap`) and `tests/test_architecture.py::_broken`") == []
    assert _broken("`sim/transfer.py`") == ["sim/transfer.py: no such file"]
    assert _broken("`sim/p2g.py` (`p2g_everything`)") == ["sim/p2g.py: defines no p2g_everything"]


def _solver_members_used() -> dict[str, str]:
    # solver.<name> in the code outside sim/: name -> first place
    used = {}
    for p in _sources():
        if SRC / "sim" in p.parents:
            continue
        for m in re.finditer(r"\bsolver\.([A-Za-z_]\w*)", p.read_text()):
            used.setdefault(m.group(1), str(p.relative_to(ROOT)))
    return used


def test_simulation_asks_the_solver_only_what_architecture_md_lists():
    text = (ROOT / "docs" / "architecture.md").read_text()
    section = text[text.index("## The solver's questions and answers"):text.index("## Segments and CUDA graphs")]
    listed = set(re.findall(r"`solver\.([A-Za-z_]\w*)", section))
    unlisted = {name: where for name, where in _solver_members_used().items() if name not in listed}
    assert not unlisted, f"solver members used but not in architecture.md's list: {unlisted}"
    assert "launcher" not in listed and len(listed) > 15
