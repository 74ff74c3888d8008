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


def _cited_commands() -> list[tuple[str, list[str]]]:
    """Each ``python -m benchmarks run NAME ARGS`` the docs cite: (NAME, the options it passes)."""
    pattern = re.compile(r"python -m benchmarks run ([a-z_]+)([^`|;#)\n]*)")
    docs = [ROOT / "README.md", *(ROOT / "docs").glob("*.md"), *(ROOT / "docs" / "decisions").glob("*.md")]
    cited = []
    for doc in docs:
        for line in doc.read_text(encoding="utf-8").splitlines():
            if "deleted on" in line:  # an archived investigation's command, kept in its record with the commit
                continue
            for name, rest in pattern.findall(line):
                cited.append((name, rest.split()))
    return cited


_HELP = """
import contextlib, io, json, runpy, sys
out = {}
for q in json.loads(sys.argv[1]):
    buf = io.StringIO()
    sys.argv = [f"benchmarks/{q[0]}.py", *q[1:], "--help"]
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        try:
            runpy.run_module(f"benchmarks.{q[0]}", run_name="__main__", alter_sys=True)
        except SystemExit:
            pass
        except Exception as e:
            buf.write(f"ERROR {e!r}")
    out[" ".join(q)] = buf.getvalue()
print(json.dumps(out))
"""


def _help_texts(queries: list[tuple[str, ...]]) -> dict[str, str]:
    """``--help`` of each (benchmark, [sub-command]) in one process (the imports once)."""
    import json

    out = subprocess.run([sys.executable, "-c", _HELP, json.dumps(queries)], cwd=ROOT, capture_output=True, text=True,
                         timeout=600, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_every_benchmark_the_docs_cite_exists_with_the_options_they_pass() -> None:
    """Issue 26: every benchmark the docs cite still runs from its documented command (its name exists; each option the
    docs pass is one its ``--help`` names, for sub-commands that sub-command's)."""
    modules = {p.stem for p in (ROOT / "benchmarks").glob("*.py") if not p.name.startswith("_")}
    cited = _cited_commands()
    assert len(cited) > 40
    missing = sorted({name for name, _ in cited if name not in modules})
    assert not missing, f"the docs cite benchmarks that do not exist: {missing}"

    queries = sorted({(name,) for name, _ in cited}
                     | {(name, args[0]) for name, args in cited if args and re.fullmatch(r"[a-z][a-z-]*", args[0])})
    helps = {tuple(q.split()): text for q, text in _help_texts(queries).items()}
    optional = ("matplotlib",)  # plot_suite's plotting library, not a dependency: read its options from the source
    broken = {q: t for q, t in helps.items() if "ERROR" in t and not any(f"No module named '{m}'" in t for m in optional)}
    assert not broken, f"benchmarks that fail before parsing their options: {broken}"
    for q, t in helps.items():
        if "ERROR" in t:
            helps[q] = (ROOT / "benchmarks" / f"{q[0]}.py").read_text(encoding="utf-8")
    unknown = []
    for name, args in cited:
        text = helps[(name,)] + (helps.get((name, args[0]), "") if args else "")
        for opt in (a.strip("[]'\"").split("=")[0] for a in args if a.lstrip("[").startswith("--")):
            if opt not in text:
                unknown.append(f"{name} {opt}")
    assert not unknown, f"options the docs pass that the benchmarks do not take: {sorted(set(unknown))}"
