"""Time from process start to the first iteration of a reconstruction on the bundled sample (issue 48, item 2).

    python -m benchmarks run cold_start [--repeats 3] [--device cpu]

Starts fresh Python processes that run ``fdt reconstruct sample_data/letters`` (the command line) or build a
``Reconstructor`` and iterate it (the Python API), and stops each at the first backward pass of the run (the first
iteration, the pupil's pilot's where it runs); prints the seconds from the process's first line (after the
interpreter's own start) to that point, and to the end of ``import napari_fdt``, as one JSON row per entry point
(benchmarks/results/cold_start_DEVICE.jsonl). Nothing is asserted; this reports.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from benchmarks._results import append_row, results_file

ROOT = Path(__file__).resolve().parents[1]

_PROBE = """
import time, sys, os
t0 = time.perf_counter()
import torch
def first_backward(self, *a, **k):
    print(json.dumps({{"imports_s": t_imported - t0, "first_iteration_s": time.perf_counter() - t0}}), flush=True)
    os._exit(0)
torch.Tensor.backward = first_backward
import json
import napari_fdt
t_imported = time.perf_counter()
{body}
"""

_BODIES = {
    "cli": "from napari_fdt.cli import main\nsys.argv = ['fdt', 'reconstruct', 'sample_data/letters', '--out', {out!r}, "
           "'--overwrite', '--device', {device!r}]\nmain()",
    "python": "from napari_fdt import read_acquisition\nfrom napari_fdt.recon.run.solver import Reconstructor\n"
              "for _ in Reconstructor(read_acquisition('sample_data/letters'), device={device!r}).run(): pass",
}


def measure(entry: str, device: str, out: str) -> dict[str, float]:
    """One fresh process of ``entry`` ("cli" or "python"): its seconds to the end of the imports and to the first iteration."""
    code = _PROBE.format(body=_BODIES[entry].format(out=out, device=device))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=600)
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    if not lines:
        raise RuntimeError(f"{entry}: no iteration reached\n{res.stderr[-2000:]}")
    return json.loads(lines[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    out = str(Path("/tmp") / "fdt_cold_start_RI.tif")
    for entry in _BODIES:
        runs = [measure(entry, args.device, out) for _ in range(args.repeats)]
        row = {"entry": entry, "repeats": args.repeats,
               "imports_s": statistics.median(r["imports_s"] for r in runs),
               "first_iteration_s": statistics.median(r["first_iteration_s"] for r in runs),
               "first_iteration_s_all": [round(r["first_iteration_s"], 3) for r in runs]}
        print(json.dumps(row))
        append_row(results_file("cold_start", args.device), row, args.device)


if __name__ == "__main__":
    main()
