"""The package's import graph: no cycles at run time (issue 26; the layers themselves are import-linter's contracts)."""

from __future__ import annotations

import pytest


def test_no_import_cycles_in_the_package() -> None:
    """No module of napari_fdt imports, at run time, one that imports it back (issue 26). The solver's helper modules
    name ``Reconstructor`` in annotations only (``if TYPE_CHECKING``), which never executes."""
    grimp = pytest.importorskip("grimp")  # (installed with import-linter, the test extra)
    graph = grimp.build_graph("napari_fdt", exclude_type_checking_imports=True)
    cycles = [(a, b) for a in sorted(graph.modules) for b in graph.find_modules_directly_imported_by(a)
              if b.startswith("napari_fdt") and graph.chain_exists(importer=b, imported=a)]
    assert not cycles, cycles


def test_no_source_file_over_600_lines() -> None:
    """Small modules with one job each (issue 26's 'no source file is over 600 lines'): the package, the benchmarks,
    the tests and the scripts."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    files = [p for d in ("src", "benchmarks", "tests", "scripts", "docs") for p in (root / d).rglob("*.py")]
    assert len(files) > 100
    long = {str(p.relative_to(root)): n for p in files if (n := len(p.read_text(encoding="utf-8").splitlines())) > 600}
    assert not long, long
