"""The package's shape (issue 52): no import circle among its modules, counting every import statement (type-only and
function-level included, which the run-time import and import-linter's layers do not all see); no source folder with
more than 15 modules; and the loop's helpers and the choices touch a run only through the members of
:class:`napari_fdt.recon.loop.interface.Run`, all of which the solver has."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "napari_fdt"
MAX_MODULES_PER_FOLDER = 15


def _modules() -> dict[str, Path]:
    """Dotted name → file of every module of the package (a package's name for its ``__init__.py``)."""
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imported(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its file (a ``from package import module`` counts as the
    module, a ``from module import name`` as the module)."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else [])) if node.level else node.module
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        else:
            continue
        found.update(t for t in targets if t in modules and t != name)
    return found


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm, iterative)."""
    index, low, on_stack, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter[0]
                    counter[0] += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[v] = min(low[v], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    out.append(sorted(component))
    return out


def test_circle_finder_finds_a_planted_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _circles(graph) == [["a", "b", "c"]]
    assert _circles({"a": {"b"}, "b": set()}) == []


def test_no_import_circle():
    modules = _modules()
    graph = {name: _imported(name, path, modules) for name, path in modules.items()}
    assert "napari_fdt.recon.run.solver" in graph["napari_fdt.recon.run.session"]  # the scan sees imports
    assert _circles(graph) == []


def test_no_folder_holds_more_than_15_modules():
    folders: dict[Path, int] = {}
    for path in PACKAGE.rglob("*.py"):
        folders[path.parent] = folders.get(path.parent, 0) + 1
    crowded = {str(f.relative_to(PACKAGE)): n for f, n in folders.items() if n > MAX_MODULES_PER_FOLDER}
    assert crowded == {}


def _run_members() -> set[str]:
    from napari_fdt.recon.loop.interface import Run

    tree = ast.parse((PACKAGE / "recon" / "loop" / "interface.py").read_text(encoding="utf-8"))
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == Run.__name__)
    names = {n.target.id for n in cls.body if isinstance(n, ast.AnnAssign)}
    return names | {n.name for n in cls.body if isinstance(n, ast.FunctionDef)}


def test_helpers_touch_a_run_only_through_its_interface():
    members = _run_members()
    used: dict[str, set[str]] = {}
    for room in ("loop", "choices"):
        for path in (PACKAGE / "recon" / room).glob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "rec":
                    used.setdefault(node.attr, set()).add(path.name)
    assert len(used) > 40  # the scan sees the helpers' use
    assert {name: files for name, files in used.items() if name not in members} == {}


@pytest.mark.filterwarnings("ignore")
def test_the_solver_has_every_member_of_the_interface(scene16):
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig, StageConfig

    rec = Reconstructor(scene16.acquisition, SolverConfig(stages=(StageConfig(1, 1),)), device="cpu")
    rec.plan  # noqa: B018 (made in the constructor)
    rec._resume_in_stage = None  # set by a resume (recon/loop/checkpoint.py), read at a stage's start
    assert sorted(m for m in _run_members() if not hasattr(rec, m)) == []


def test_no_source_file_over_600_lines() -> None:
    """Small modules with one job each (issue 26's 'no source file is over 600 lines'): the package, the benchmarks,
    the tests and the scripts."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    files = [p for d in ("src", "benchmarks", "tests", "scripts", "docs") for p in (root / d).rglob("*.py")]
    assert len(files) > 100
    long = {str(p.relative_to(root)): n for p in files if (n := len(p.read_text(encoding="utf-8").splitlines())) > 600}
    assert not long, long
