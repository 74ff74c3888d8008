"""The benchmarks are a package with one entry point (issue 26): ``python -m benchmarks list`` names each benchmark and
what it measures, and neither the benchmarks nor the tests edit the import path to reach each other."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_list_names_every_benchmark_and_what_it_measures() -> None:
    out = subprocess.run([sys.executable, "-m", "benchmarks", "list"], cwd=ROOT, capture_output=True, text=True, check=True,
                         timeout=120).stdout
    listed = {line.split()[0]: line.split(None, 1)[1] for line in out.splitlines() if line.strip()}
    modules = {p.stem for p in (ROOT / "benchmarks").glob("*.py") if not p.name.startswith("_")}
    assert set(listed) == modules
    assert all(len(text) > 20 for text in listed.values())  # each with its docstring's first line
    bad = subprocess.run([sys.executable, "-m", "benchmarks", "run", "no_such_benchmark"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and "python -m benchmarks list" in bad.stderr


def test_no_import_path_edits() -> None:
    edit = re.compile(r"sys\.path\.(insert|append)\(")
    files = [*(ROOT / "benchmarks").glob("*.py"), *(ROOT / "tests").glob("*.py")]
    assert not [f.name for f in files if edit.search(f.read_text(encoding="utf-8"))]

