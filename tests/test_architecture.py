"""The house rules of the code base, checked (docs/architecture.md):

* the import contracts of pyproject.toml (``[tool.importlinter]``): ``sim/`` imports
  nothing above it, and the layers scene -> geometry -> solver inputs -> step ->
  writers -> commands, checked by import-linter;
* no import cycle between modules, function-local imports included (grimp);
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


def _cycle_through(graph, importer: str, imported: str) -> list[str] | None:
    # importer imports imported directly; a chain back from imported closes a cycle
    chain = graph.find_shortest_chain(importer=imported, imported=importer)
    return [importer, *chain] if chain else None


def test_no_import_cycles():
    """No module is reached again from what it imports, counting imports inside
    functions too (a cycle held up by function-local imports is still a cycle)."""
    graph = grimp.build_graph("abmpm", cache_dir=None)
    cycles = []
    for importer in sorted(graph.modules):
        for imported in sorted(graph.find_modules_directly_imported_by(importer)):
            cycle = _cycle_through(graph, importer, imported)
            if cycle:
                cycles.append(" -> ".join(cycle))
    assert not cycles, "import cycles:\n" + "\n".join(cycles[:10])


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
    # relative to the repository, to src/abmpm, or a bare file name anywhere in src/abmpm
    for base in (ROOT, SRC, SRC.parent):
        if (base / ref).is_file():
            return [base / ref]
    return sorted(SRC.rglob(ref)) if "/" not in ref else []


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
