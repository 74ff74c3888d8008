"""A stack at the paper's full size (1521 images of 512×512 px, uint16, 0.8 GB): peak memory and time of `fdt info`,
`fdt plan` and the solver's set-up, each in its own process (issue 28, item 3; docs/hard_cases.md).

    python -m benchmarks run full_size_stack [--folder /tmp/full_size] [--write]

The stack is noise-like images on the authors' demo geometry (λ 0.6 µm, NA 0.65, 14 slices of 1.5 µm, a 39×39 grid of
sources 50 µm deep spanning ±42 µm), written uncompressed as `write_acquisition` and most acquisition software do.
``--write`` replaces the block between the ``full-size`` markers of docs/hard_cases.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import tifffile

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "hard_cases.md"
START, END = "<!-- full-size:start -->", "<!-- full-size:end -->"

SET_UP = """
import sys
from napari_fdt.data.io import read_acquisition
from napari_fdt.recon.settings.config import SolverConfig
from napari_fdt.recon.run.solver import Reconstructor
acq = read_acquisition(sys.argv[1])
rec = Reconstructor(acq, SolverConfig(snapshot_every=1), device="cpu")
n = int(sys.argv[2])  # iterations of the first stage to run (its block averages built), 0: none
for k, _ in enumerate(rec.run() if n else ()):
    if k == n - 1:
        break
"""


def make_stack(folder: Path, n_side: int = 39, side: int = 512) -> Path:
    """Write the full-size acquisition (noise-like uint16 images) unless ``folder`` already holds it."""
    if (folder / "images.tif").exists():
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    g = np.linspace(-42.0, 42.0, n_side)
    yy, xx = np.meshgrid(g, g, indexing="ij")
    n = n_side * n_side
    meta = {"format": "fdt-acquisition", "version": 1, "images": "images.tif", "wavelength_um": 0.6,
            "n_background": 1.33, "na": 0.65, "pixel_size_um": 0.33, "n_slices": 14, "slice_spacing_um": 1.5,
            "image_plane_um": 10.5, "sources_um": np.column_stack([xx.ravel(), yy.ravel(), np.full(n, 50.0)]).tolist()}
    (folder / "acquisition.json").write_text(json.dumps(meta))
    rng = np.random.default_rng(0)
    with tifffile.TiffWriter(folder / "images.tif", bigtiff=True) as tw:
        for _ in range(n):
            tw.write(rng.integers(100, 4000, size=(side, side), dtype=np.uint16), contiguous=True, photometric="minisblack")
    return folder


def measured(argv: list[str]) -> dict:
    """Peak resident memory (MB) and wall time (s) of a child process running ``argv``, and its output."""
    probe = ("import resource, subprocess, sys, time; t = time.perf_counter(); "
             "out = subprocess.run(sys.argv[1:], check=True, capture_output=True, text=True).stdout; "
             "print(repr(out)); print(time.perf_counter() - t); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)")
    lines = subprocess.run([sys.executable, "-c", probe, *argv], check=True, capture_output=True, text=True).stdout.splitlines()
    return {"output": eval(lines[-3]), "wall_s": round(float(lines[-2]), 2), "peak_mb": round(float(lines[-1]))}  # noqa: S307


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folder", type=Path, default=Path("/tmp/fdt_full_size"))
    ap.add_argument("--write", action="store_true", help="write the table into docs/hard_cases.md")
    args = ap.parse_args()
    t = time.perf_counter()
    folder = make_stack(args.folder)
    print(f"stack ready in {time.perf_counter() - t:.0f} s: {folder}", flush=True)
    fdt = [sys.executable, "-c", "import sys; from napari_fdt.cli import main; sys.exit(main(sys.argv[1:]))"]
    rows = {
        "imports only (`import napari_fdt.cli`, torch included)": measured([sys.executable, "-c", "import napari_fdt.cli, napari_fdt.physics.grid"]),
        "`fdt info FOLDER`": measured([*fdt, "info", str(folder)]),
        "`fdt plan FOLDER --device cpu`": measured([*fdt, "plan", str(folder), "--device", "cpu"]),
        "read + `Reconstructor(acq, device=\"cpu\")` (set-up: the mean, the checks, the plan)": measured([sys.executable, "-c", SET_UP, str(folder), "0"]),
        # the first snapshot: the x4 stage's set-up (its block averages, the gains) and 10 steps of the pupil's pilot,
        # which runs the finest stage's model (before the pilot existed, 2026-11-26: 3 iterations of the x4 stage)
        "the same, to the first snapshot (the ×4 stage's set-up, 10 steps of the pupil's pilot at ×1)":
            measured([sys.executable, "-c", SET_UP, str(folder), "1"]),
    }
    for name, r in rows.items():
        print(f"{name}: peak {r['peak_mb']} MB, {r['wall_s']} s", flush=True)
    plan = rows["`fdt plan FOLDER --device cpu`"]["output"].strip().splitlines()
    size_gb = (folder / "images.tif").stat().st_size / 1e9
    table = [
        START,
        "## A full-size stack (issue 28)",
        "",
        f"Made by `python -m benchmarks run full_size_stack --write` on {platform.machine()}, {time.strftime('%Y-%m-%d')}, "
        f"2 CPU cores: a {size_gb:.2f} GB stack of 1521 images of 512×512 px (uint16, uncompressed) on the demo "
        "geometry. Each command in its own process; peak resident memory from `getrusage` (file pages of the mapped "
        "stack that were read count too).",
        "",
        "| command | peak resident memory (MB) | wall time (s) |",
        "|---|---|---|",
        *[f"| {name} | {r['peak_mb']} | {r['wall_s']} |" for name, r in rows.items()],
        "",
        "The stack is a read-only memory map of the file (`napari_fdt.data.mapped`): `fdt info` and `fdt plan` read the "
        "header and the JSON, the napari reader hands napari the map (it reads the planes it shows), and what must see "
        "every pixel (NaN and negative checks, blank and saturated images, the mean) goes through it in chunks of "
        "64 MB. The solver reads each batch's rows from it (`napari_fdt.recon.problem.stage_images`: no float32 copy of the "
        "stack on the CPU; a coarse stage holds its block averages, a GPU stage the stack on the device). With the "
        "version before (commit 4873372, measured the same day) `fdt info` peaked at 1,020 MB and the solver's set-up "
        "at 4,047 MB (three float32 copies). The plugin's computation process receives the file reference, not a "
        "pickled copy of the pixels. The first snapshot's peak is the pilot's: the finest stage's model (its 600² "
        "window, 14 slices, the camera's pixel means) on 16 images, plus the stack's file pages its checks read. Its "
        "training step alone grows the process by 1.2-1.4 GB (`python -m benchmarks run training_memory "
        "FOLDER`), which the plan's peak below now bounds; before 2026-11-29 the plan left the pixel means out and said "
        "0.89 GiB. With `coherence` \"mask\", the masks of all 1521 sources were imaged in one pass and the process was "
        "killed by the kernel at 24 GB (2026-11-29); they are now made 16 at a time (`model/coherence.MASK_BATCH`): the "
        "finest stage run alone then peaked at 4.6 GB, about 4 minutes of it the masks.",
        "",
        "`fdt plan` on this stack (what `fdt reconstruct` prints first, `--quiet` included, with the warning that a CPU "
        "run takes over 30 minutes):",
        "",
        *["    " + line for line in plan],
        END,
    ]
    block = "\n".join(table)
    print(block)
    if args.write:
        text = DOC.read_text(encoding="utf-8")
        if START in text:
            text = re.sub(re.escape(START) + ".*?" + re.escape(END), lambda _: block, text, flags=re.S)
        else:
            text = text.rstrip("\n") + "\n\n" + block + "\n"
        DOC.write_text(text, encoding="utf-8")
        print(f"wrote {DOC}")


if __name__ == "__main__":
    main()
