"""Peak memory of one training step of the finest stage against the estimate the memory check and `fdt plan` use.

    python -m benchmarks run training_memory [ACQ ...] [--field-window full|auto]

For each acquisition (default: the bundled sample, out/scenes/cells_pupil where present) and the camera's pixel
integration off and on, a fresh process builds the finest stage run alone (``benchmarks/step_profile_cpu.py``'s
``finest_stage_step``: factor 1, batch 16, the pupil and the coherence masks off), resets the peak resident set
(``/proc/self/clear_refs``) and reads its growth over the first two steps (``VmHWM``): what a step holds, the
optimiser's state included (the allocator keeps what the first step freed, so later steps alone would read less). Printed beside it:
``napari_fdt.recon.problem.preflight.finest_stage_bytes``, the estimate (its images on the device excluded: none on
the CPU). Linux only (``/proc``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _status_mib(key: str) -> float:
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"{key} not in /proc/self/status")


def measure(acquisition: str, pixel_integration: bool, field_window: str = "full") -> dict:
    """In this process (call it in a fresh one): the finest step's peak growth and the estimate, bytes."""
    import gc
    import warnings

    import torch

    from benchmarks.step_profile_cpu import finest_stage_step
    from napari_fdt.data.io import read_acquisition
    from napari_fdt.recon.problem.preflight import finest_stage_bytes

    warnings.simplefilter("ignore")
    torch.set_num_threads(2)
    acq = read_acquisition(acquisition)
    step, rec, stage = finest_stage_step(acq, pixel_integration="true" if pixel_integration else "false",
                                         calibrate_pupil=False, coherence="none", field_window=field_window)
    need, plan, batch, mode = finest_stage_bytes(acq, rec.config, rec.initial_sources_um, 1, "cpu")
    gc.collect()
    with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
        f.write("5")  # VmHWM := VmRSS
    before = _status_mib("VmRSS")
    step()
    step()
    grown = (_status_mib("VmHWM") - before) * 2**20
    return {"acquisition": acquisition, "pixel_integration": pixel_integration, "model": type(stage.model).__name__,
            "window": list(plan.padded_shape), "batch": batch, "mode": mode, "measured_bytes": int(grown),
            "estimate_bytes": int(need)}


def measure_in_fresh_process(acquisition: str, pixel_integration: bool, field_window: str = "full") -> dict:
    """:func:`measure` in a fresh Python process (a peak is only clean there)."""
    code = ("import json, sys; from benchmarks.training_memory import measure; "
            f"print(json.dumps(measure({acquisition!r}, {pixel_integration!r}, {field_window!r})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=600, cwd=ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("acquisitions", nargs="*")
    ap.add_argument("--field-window", default="full", choices=["full", "auto"])
    args = ap.parse_args()
    acqs = args.acquisitions or [str(p) for p in (ROOT / "sample_data" / "letters", ROOT / "out" / "scenes" / "cells_pupil")
                                 if (p / "acquisition.json").is_file()]
    print("| acquisition | model | window | batch | backward | pixel integration | measured MiB | estimate MiB | estimate / measured |")
    print("|---|---|---|---|---|---|---|---|---|")
    for acq in acqs:
        for pi in (False, True):
            r = measure_in_fresh_process(acq, pi, args.field_window)
            m, e = r["measured_bytes"] / 2**20, r["estimate_bytes"] / 2**20
            print(f"| {Path(acq).name} | {r['model']} | {r['window'][0]}x{r['window'][1]} | {r['batch']} | {r['mode']} | "
                  f"{'on' if pi else 'off'} | {m:.0f} | {e:.0f} | {e / m:.2f} |", flush=True)


if __name__ == "__main__":
    main()
