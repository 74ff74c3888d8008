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



def test_results_are_written_in_one_format(tmp_path: Path) -> None:
    """Every result goes through ``benchmarks._results``: a table row carries the machine's fields unless it sets them,
    a document is ``{"hardware": ..., ...}`` written atomically; no benchmark opens a results file by itself."""
    import json

    from benchmarks._results import append_row, read_rows, results_file, write_document

    table = tmp_path / "t.jsonl"
    append_row(table, {"scene": "a", "date": "2026-01-01"})
    append_row(table, {"scene": "b"})
    rows = read_rows(table)
    assert [r["scene"] for r in rows] == ["a", "b"]
    assert rows[0]["date"] == "2026-01-01"  # the row's own value wins
    assert {"device", "cpu", "threads", "torch", "commit", "command"} <= set(rows[1])
    doc = write_document(tmp_path / "d.json", {"hardware": {"name": "mine"}, "rows": [1, 2]})
    data = json.loads(doc.read_text())
    assert data["rows"] == [1, 2] and data["hardware"]["name"] == "mine" and data["hardware"]["threads"] >= 1
    assert not list(tmp_path.glob("*.tmp"))
    assert results_file("suite", "cuda:0", table=False).name == "suite_cuda.json"
    by_hand = re.compile(r'open\("a"\)|/ "results"')
    writers = [p.name for p in (ROOT / "benchmarks").glob("*.py") if p.name != "_results.py" and by_hand.search(p.read_text())]
    assert not writers, f"write results through benchmarks._results: {writers}"
