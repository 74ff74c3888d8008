"""The benchmarks' one results format: where results go, what each says about the machine and the code, how it is
written (issue 26).

Everything is JSON under ``benchmarks/results/``, named after the benchmark and the device kind, in one of two shapes:

* a **table of runs**, ``NAME_DEVICE.jsonl``: one JSON object per run, appended (a rerun adds a row; readers keep the
  last row of each key), each row carrying the :func:`machine` fields flat (``device``, ``name``, ``cpu``,
  ``threads``, ``torch``, ``date``, ``commit``, ``command``, ...) unless the row sets them itself;
* a **document**, ``NAME_DEVICE.json``: one object ``{"hardware": machine(...), ...}``, rewritten whole and atomically
  (a temporary file, then a rename), for benchmarks whose result is one table made in one process.

Rows written before this module keep their keys (``cpu``, ``threads``, ``torch``, ``date`` were already common to
them); the readers of the docs' tables use only those.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

__all__ = ["RESULTS", "machine", "code_version", "command", "results_file", "append_row", "read_rows", "write_document"]

ROOT = Path(__file__).resolve().parents[1]
#: where every benchmark writes its results
RESULTS = ROOT / "benchmarks" / "results"


def code_version() -> str:
    """The commit the code was run at (``git describe --always --dirty``; ``"unknown"`` outside a checkout)."""
    try:
        return subprocess.run(["git", "describe", "--always", "--dirty"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def command() -> str:
    """The command line that made the result, as the docs cite it (``python -m benchmarks run NAME ...``)."""
    argv = list(sys.argv)
    first = Path(argv[0]) if argv else Path("?")
    if first.parent.name == "benchmarks" and first.suffix == ".py":
        return " ".join(["python -m benchmarks run", first.stem, *argv[1:]])
    return " ".join(["python", *argv])


def machine(device: str | torch.device = "cpu") -> dict[str, Any]:
    """The machine, versions, date, commit and command of a result (the ``hardware`` of a document, a row's flat fields)."""
    dev = torch.device(device)
    cuda = dev.type == "cuda" and torch.cuda.is_available()
    cpu = platform.processor() or platform.machine()
    return {
        "device": str(device), "name": torch.cuda.get_device_name(dev) if cuda else cpu, "cpu": cpu,
        "machine": platform.machine(), "cpu_count": os.cpu_count(), "threads": torch.get_num_threads(),
        "torch": torch.__version__, "python": platform.python_version(), "date": time.strftime("%Y-%m-%d %H:%M"),
        "commit": code_version(), "command": command(),
    }


def results_file(name: str, device: str | torch.device = "cpu", table: bool = True) -> Path:
    """``benchmarks/results/NAME_DEVICE.jsonl`` (a table of runs) or ``.json`` (a document); DEVICE the kind (cpu, cuda)."""
    kind = torch.device(device).type
    return RESULTS / f"{name}_{kind}.{'jsonl' if table else 'json'}"


def append_row(path: Path, row: dict[str, Any], device: str | torch.device = "cpu") -> Path:
    """Append one run's row to the table ``path``, with the :func:`machine` fields it does not set itself."""
    full = {**row, **{k: v for k, v in machine(device).items() if k not in row}}
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", encoding="utf-8") as f:
        f.write(json.dumps(full, default=float) + "\n")
    return path


def read_rows(path: Path) -> list[dict[str, Any]]:
    """Every row of a table (none when the file does not exist); blank lines skipped."""
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def write_document(path: Path, payload: dict[str, Any], device: str | torch.device = "cpu") -> Path:
    """Write ``{"hardware": machine(device), **payload}`` to ``path`` atomically (a temporary file, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {**payload, "hardware": {**machine(device), **payload.get("hardware", {})}}
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1, default=float) + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path
