"""The half-set resolution checked against the truth (issue 25): ``fdt reconstruct --half-set-resolution --truth``.

    python -m benchmarks run half_set_resolution run --scenes sample,cells,beads,deep,letters128 --seeds 0,1 [--jobs 2]
    python -m benchmarks run half_set_resolution table
    python -m benchmarks run half_set_resolution run --scenes sample,cells --seeds 0 --tv 1,3,10   # fixed TV weights
    python -m benchmarks run half_set_resolution tv                                            # the FSC as a TV rule

``run`` reconstructs each scene and seed with the defaults and ``--half-set-resolution`` (one thread per run, ``--jobs``
runs at a time) and keeps from its report: the half-set figures (lateral, axial; ``resolved_to_grid`` where the halves
agree up to the grid), the truth's own (the FSC of the result with the truth at 0.5, ``metrics.resolution_against_truth``),
the relative Δn error, the run's and the halves' seconds. One row per run in
``benchmarks/results/half_set_resolution_cpu.jsonl``. ``table`` prints the Markdown table of
docs/decisions/tv-half-sets.md, section 8 (the last row of each scene and seed; rows with the automatic TV weight).
With ``--tv`` the runs are at fixed weights (τ_xy = τ, τ_z = τ/2) instead, and ``tv`` prints, per scene and seed, each
weight's Δn error beside the halves' mean FSC (lateral, axial): does the halves' agreement rank the weights as the truth
does (section 7)?
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from benchmarks._results import append_row, read_rows, results_file
from benchmarks.scenes import folder_of

OUT = results_file("half_set_resolution", "cpu")


def run_one(scene: str, seed: int, tv: float | None = None) -> dict:
    folder = folder_of(scene)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "ri.tif"
        cmd = [sys.executable, "-m", "napari_fdt", "reconstruct", str(folder), "--out", str(out), "--seed", str(seed),
               "--quiet", "--device", "cpu", "--half-set-resolution", "--truth", str(folder / "ground_truth_ri.tif")]
        if tv is not None:
            cmd += ["--tv-xy-weight", str(tv), "--tv-z-weight", str(tv / 2)]
        subprocess.run(cmd, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True)
        report = json.loads(out.with_suffix(".json").read_text())
    res, truth = report["resolution"], report["metrics"]["resolution_against_truth"]
    row = {"scene": scene, "seed": seed, "setting": "auto" if tv is None else tv, "relative_delta_n_error": report["metrics"]["relative_delta_n_error"],
           "run_s": report["seconds_total"], "halves_s": res["seconds"], "tv_xy_weight": report["regularisation"]["tv_xy_weight"],
           "parts": report["model_parts"]["needed"]}
    for d in ("lateral", "axial"):
        h, t = res["directions"][d], truth[d]
        row[d] = {"resolution_um": h["resolution_um"], "limited_by": h["limited_by"], "half_sets_um": h["half_sets_um"],
                  "band_limit_um": h["band_limit_um"], "truth_um": t["resolution_um"], "grid_um": h["grid_limit_um"],
                  "fsc_halves": h["fsc"]["correlation"], "frequency_per_um": h["fsc"]["frequency_per_um"]}
    return row


def _figure(um: float | None, grid: float) -> str:
    return f"≤ {grid:g} (grid)" if um is None else f"{um:.2f}"


def _reported(scene: str, cell: dict) -> tuple[float, str]:
    """The figure the report gives and what sets it. Rows of 2026-11-27 07:38-07:45 were made before the band limit
    was part of it: for them :func:`napari_fdt.recon.run.half_sets.resolution_figure` applies it here as the report does."""
    if "limited_by" in cell:
        return cell["resolution_um"], cell["limited_by"]
    from napari_fdt import read_acquisition
    from napari_fdt.physics.band import band_limit_per_um
    from napari_fdt.recon.run.half_sets import resolution_figure

    acq = read_acquisition(folder_of(scene))
    axis = "lateral" if cell["grid_um"] == 2 * acq.optics.pixel_size_um else "axial"
    band_um = 1.0 / band_limit_per_um(acq.optics, acq.image_shape, acq.sources_um)[axis]
    return resolution_figure(cell["half_sets_um"], cell["grid_um"], band_um)


def table() -> str:
    rows: dict[tuple[str, int], dict] = {}
    for r in read_rows(OUT):
        if r.get("setting", "auto") == "auto":
            rows[(r["scene"], r["seed"])] = r
    lines = ["| scene | seed | Δn error | lateral µm: halves | reported (set by) | truth | axial µm: halves | reported (set by) | truth "
             "| run s | halves s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for (scene, seed), r in sorted(rows.items()):
        cells = []
        for d in ("lateral", "axial"):
            c = r[d]
            um, by = _reported(scene, c)
            cells += [_figure(c["half_sets_um"], c["grid_um"]), f"{'≤ ' if by == 'grid' else ''}{um:.2f} ({by})",
                      _figure(c["truth_um"], c["grid_um"])]
        lines.append(f"| {scene} | {seed} | {r['relative_delta_n_error']:.3f} | {' | '.join(cells)} | {r['run_s']:.0f} | "
                     f"{r['halves_s']:.0f} |")
    return "\n".join(lines)


def tv_table() -> str:
    """Per scene and seed, each fixed weight's Δn error and the halves' mean FSC over the bins after the first."""
    rows: dict[tuple[str, int, float], dict] = {}
    for r in read_rows(OUT):
        if r.get("setting", "auto") != "auto":
            rows[(r["scene"], r["seed"], float(r["setting"]))] = r
    lines = ["| scene | seed | τ | Δn error | halves' mean FSC, lateral | axial |", "|---|---|---|---|---|---|"]
    for (scene, seed, tau), r in sorted(rows.items()):
        lat, ax = (sum(r[d]["fsc_halves"][1:]) / (len(r[d]["fsc_halves"]) - 1) for d in ("lateral", "axial"))
        lines.append(f"| {scene} | {seed} | {tau:g} | {r['relative_delta_n_error']:.3f} | {lat:.3f} | {ax:.3f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--scenes", default="sample,cells,beads,deep,letters128")
    r.add_argument("--seeds", default="0,1")
    r.add_argument("--jobs", type=int, default=2)
    r.add_argument("--tv", default=None, help="fixed TV weights τ_xy, comma-separated (τ_z = τ/2); default: the automatic choice")
    sub.add_parser("table")
    sub.add_parser("tv")
    args = ap.parse_args()
    if args.cmd in ("table", "tv"):
        print(table() if args.cmd == "table" else tv_table())
        return
    taus = [None] if args.tv is None else [float(t) for t in args.tv.split(",")]
    todo = [(s, int(seed), tau) for s in args.scenes.split(",") for seed in args.seeds.split(",") for tau in taus]

    def one(job: tuple[str, int, float | None]) -> None:
        row = run_one(*job)
        append_row(OUT, row)
        print(json.dumps({k: v for k, v in row.items() if k not in ("lateral", "axial")}), flush=True)

    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(one, todo))


if __name__ == "__main__":
    main()
