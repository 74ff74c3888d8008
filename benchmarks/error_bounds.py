"""Per-voxel error bounds in RI units (issue 50): scenes, reconstructions, re-simulations, then calibration and coverage.

Question: can a per-voxel bound U(v) with |Δn_result − Δn_true| ≤ U(v) on about 90 % of the support be made from
what a run can compute, on scenes nobody tuned to, without being vacuous (mean U ≤ 3× mean |error|)?

``make``: simulated scenes of four families (beads, cells, fibres in thick slices, letters), each made with the
accurate forward model (4 sub-slices per slice, the field on a 2× grid: not the solver's own model), with faint beads
(Δn 0.002–0.02) planted at half of eight sites, half of the sites in the axial shadow of a larger object; the sites
are written beside the truth (``sites.json``).

``run``: per scene, the default reconstruction (one thread), then the product's K re-simulations of the result
(:func:`napari_fdt.recon.run.error_bounds.replicate_volumes`: the images the result predicts plus fresh noise at the
data's fitted level, each reconstructed from the run's start with its choices fixed). Arrays go to
``out/error_bounds/NAME/arrays.npz``, a row per scene to ``benchmarks/results/error_bounds_cpu.jsonl``.

``halves``: the negative control, each scene's images in two halves reconstructed with the run's choices (as the
half-set resolution does), added to the arrays.

``table`` (:mod:`benchmarks._error_bounds_table`): raw scores from the arrays, split-conformal calibration on half the
scenes, coverage by region on the other half and on a family left out, width against error, planted-bead calls.

    python -m benchmarks run error_bounds make --families beads,cells,fibres,letters --seeds 0-7
    python -m benchmarks run error_bounds run --families beads,cells,fibres,letters --seeds 0-7 [--replicates 3]
    python -m benchmarks run error_bounds halves --seeds 0-7
    python -m benchmarks run error_bounds table [--write]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks._results import ROOT, append_row, read_rows, results_file

RESULTS = results_file("error_bounds")
OUT = ROOT / "out" / "error_bounds"

#: family → the scene's geometry (48² px, 6 slices, 6×6 sources 30 µm deep: the suite's beads and cells made smaller,
#: so that 32 scenes and their re-simulations run in under an hour on two cores)
FAMILIES: dict[str, dict] = {
    "beads": dict(slice_spacing_um=2.0, image_plane_um=0.0),
    "cells": dict(slice_spacing_um=2.0, image_plane_um=0.0),
    # thick slices, the focus inside the volume: the suite's fibres_thick
    "fibres": dict(slice_spacing_um=3.0, image_plane_um=9.0),
    "letters": dict(slice_spacing_um=2.0, image_plane_um=0.0),
}
SHAPE, N_SLICES, SOURCES, DEPTH_UM = (48, 48), 6, 6, 30.0
#: planted faint beads: radius µm, Δn range (log-uniform), sites per scene (half planted, half left empty)
BEAD_RADIUS_UM, BEAD_DELTA_N, N_SITES = 0.8, (0.002, 0.02), 8


def _optics(family: str):
    from napari_fdt.physics.optics import Optics

    g = FAMILIES[family]
    return Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=N_SLICES,
                  slice_spacing_um=g["slice_spacing_um"], image_plane_um=g["image_plane_um"])


def _phantom(family: str, optics, rng: np.random.Generator) -> np.ndarray:
    from napari_fdt.sim.phantoms import text_phantom
    from napari_fdt.sim.simulate import make_scene

    if family == "letters":
        text = "".join(rng.choice(list("ABCDEFGHKLMNPRSTUVWXYZ"), 3))
        return text_phantom(SHAPE, N_SLICES, text=text, delta_n=0.03, letter_height_px=18,
                            first_slice=int(rng.integers(0, 2)))
    return make_scene(family, SHAPE, optics, rng=rng)


def plant_sites(dn: np.ndarray, optics, rng: np.random.Generator) -> tuple[np.ndarray, list[dict]]:
    """Δn with faint beads planted at half of :data:`N_SITES` sites; the sites as dicts (voxel, Δn planted or 0,
    whether in the axial shadow of a larger object: under or over a column whose Δn reaches half the volume's max)."""
    from scipy import ndimage

    from napari_fdt.sim.phantoms import _soft_ellipsoid, _voxel_centres

    dx, dz = optics.pixel_size_um, optics.slice_spacing_um
    occupied = dn > 1e-4
    reach = int(np.ceil(2.0 / dx))  # keep 2 µm laterally from any object
    occupied = ndimage.maximum_filter(occupied, size=(1, 2 * reach + 1, 2 * reach + 1))
    column = dn.max(axis=0)
    shadow_col = ndimage.maximum_filter(column, size=3) >= 0.5 * dn.max()
    margin = int(np.ceil(2.0 / dx))
    inner = np.zeros(dn.shape, bool)
    inner[:, margin:-margin, margin:-margin] = True
    free = inner & ~occupied
    kinds = {"shadow": np.argwhere(free & shadow_col[None]), "open": np.argwhere(free & (column < 1e-4)[None])}
    sites: list[dict] = []
    chosen: list[np.ndarray] = []
    planted_flags = rng.permutation([True, False] * (N_SITES // 4) * 2)
    for i in range(N_SITES):
        # a site at least 3 µm from the others, of the kind wanted where one is left, else of the other kind
        kind = "shadow" if i % 2 == 0 else "open"
        v = None
        for k in (kind, "open" if kind == "shadow" else "shadow"):
            cand = kinds[k]
            if len(cand) == 0:
                continue
            pos_all = cand * np.array([dz, dx, dx])
            far = np.all([np.linalg.norm(pos_all - c, axis=1) >= 3.0 for c in chosen], axis=0) if chosen else np.ones(len(cand), bool)
            if far.any():
                v, kind = cand[rng.choice(np.flatnonzero(far))], k
                break
        if v is None:
            continue
        chosen.append(v * np.array([dz, dx, dx]))
        planted = bool(planted_flags[i])
        value = float(np.exp(rng.uniform(*np.log(BEAD_DELTA_N)))) if planted else 0.0
        sites.append({"voxel": [int(a) for a in v], "kind": kind, "delta_n": value})
    out = dn.astype(np.float64).copy()
    z, y, x = _voxel_centres(dn.shape[1:], dn.shape[0], dx, dz)
    for s in sites:
        if s["delta_n"] > 0:
            k, i, j = s["voxel"]
            centre = ((k + 0.5) * dz, (i - dn.shape[1] // 2) * dx, (j - dn.shape[2] // 2) * dx)
            occ = _soft_ellipsoid(z, y, x, centre, (BEAD_RADIUS_UM,) * 3, 0.0, dx)
            out = np.maximum(out, s["delta_n"] * occ)
    return out.astype(np.float32), sites


def _simulate_into(folder: Path, dn: np.ndarray, optics, sources_um: np.ndarray, seed: int) -> None:
    from napari_fdt.data.io import write_acquisition, write_volume_tiff
    from napari_fdt.sim.simulate import simulate

    sim = simulate(dn, optics, sources_um, seed=seed, device="cpu", sub_slices=4, field_oversampling=2)
    write_acquisition(sim.acquisition, folder, overwrite=True)
    write_volume_tiff(folder / "ground_truth_ri.tif", sim.ri,
                      (optics.slice_spacing_um, optics.pixel_size_um, optics.pixel_size_um), overwrite=True)


def scene_name(family: str, seed: int) -> str:
    return f"{family}_{seed}"


def make(family: str, seed: int) -> Path:
    """The scene ``family_seed`` (acquisition, truth, sites) under :data:`OUT`; made once."""
    from napari_fdt.sim.simulate import source_grid

    folder = OUT / scene_name(family, seed) / "scene"
    if (folder / "sites.json").exists():
        return folder
    optics = _optics(family)
    rng = np.random.default_rng(1000 * seed + sorted(FAMILIES).index(family))
    dn, sites = plant_sites(_phantom(family, optics, rng), optics, rng)
    sources = source_grid(SOURCES, 0.8 * min(SHAPE) * optics.pixel_size_um, DEPTH_UM)
    _simulate_into(folder, dn, optics, sources, seed)
    (folder / "sites.json").write_text(json.dumps({"sites": sites}, indent=1))
    return folder


def _delta_n(path: Path, n_background: float) -> np.ndarray:
    from napari_fdt.data.volumes import read_volume

    return read_volume(path)[0].astype(np.float32) - np.float32(n_background)


def run(family: str, seed: int, replicates: int) -> dict:
    """The default run of a scene (one thread) and the product's ``replicates`` re-simulated runs
    (:func:`napari_fdt.recon.run.error_bounds.replicate_volumes`); arrays saved, a row back."""
    import torch

    from napari_fdt.data.io import read_acquisition
    from napari_fdt.recon.run.error_bounds import replicate_volumes
    from napari_fdt.recon.run.report import build_report
    from napari_fdt.recon.run.session import open_run
    from napari_fdt.recon.settings.config import SolverConfig

    torch.set_num_threads(1)
    folder = make(family, seed)
    work = OUT / scene_name(family, seed)
    optics = _optics(family)
    truth = _delta_n(folder / "ground_truth_ri.tif", optics.n_background)
    rec = open_run(read_acquisition(folder), SolverConfig(seed=seed), device="cpu")
    t0 = time.perf_counter()
    for _ in rec.run():
        pass
    seconds = time.perf_counter() - t0
    report = build_report(rec, cancelled=False)
    result = rec.delta_n_full()
    t0 = time.perf_counter()
    reps, noise = replicate_volumes(rec, replicates)
    rep_seconds = time.perf_counter() - t0
    sites = json.loads((folder / "sites.json").read_text())["sites"]
    np.savez_compressed(work / "arrays.npz", truth=truth, result=result, replicates=reps)
    row = {"scene": scene_name(family, seed), "family": family, "seed": seed, "replicates": replicates,
           "run_s": round(seconds, 1), "replicates_s": round(rep_seconds, 1), "noise_model": list(noise),
           "tv_xy_weight": report["regularisation"]["tv_xy_weight"], "tv_z_weight": report["regularisation"]["tv_z_weight"],
           "parts": report["model_parts"]["needed"], "validation_error": (report.get("validation") or {}).get("error"),
           "relative_error": float(np.linalg.norm(result - truth) / np.linalg.norm(truth)), "sites": sites}
    append_row(RESULTS, row)
    return row


def halves(family: str, seed: int) -> None:
    """The negative control: the scene's images in two halves (:func:`napari_fdt.recon.assess.validation.split_halves`,
    as the half-set resolution splits them), each reconstructed with the run's choices fixed (its TV weights and the
    parts it kept, from its row) from the acquisition's start; the two Δn volumes added to the scene's arrays."""
    import dataclasses
    import warnings

    import torch

    from napari_fdt.data.acquisition import Acquisition
    from napari_fdt.data.io import read_acquisition
    from napari_fdt.recon.assess.validation import split_halves
    from napari_fdt.recon.loop.model_parts import SETTING_OF
    from napari_fdt.recon.problem.stage_spec import AUTO_SUB_SLICES
    from napari_fdt.recon.run.family import parts_off
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig

    torch.set_num_threads(1)
    name = scene_name(family, seed)
    work = OUT / name
    arrays = dict(np.load(work / "arrays.npz"))
    if "halves" in arrays:
        return
    row = [r for r in read_rows(RESULTS) if r.get("scene") == name and "parts" in r][-1]
    on = {"sub_slices": AUTO_SUB_SLICES, "field_grid": 2, "obliquity": "true", "spectral": "auto", "pupil": "true",
          "aberrations": "true"}
    config = dataclasses.replace(parts_off(SolverConfig(seed=seed, parts_pilot=False)), tv_xy_weight=row["tv_xy_weight"],
                                 tv_z_weight=row["tv_z_weight"], **{SETTING_OF[p]: on[p] for p in row["parts"]})
    acq = read_acquisition(work / "scene")
    vols = []
    for idx in split_halves(acq.sources_um, seed):
        sub = Acquisition(images=acq.images[idx], optics=acq.optics, sources_um=acq.sources_um[idx], extra=dict(acq.extra))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rec = Reconstructor(sub, config, device="cpu")
            for _ in rec.run():
                pass
        vols.append(rec.delta_n_full())
    np.savez_compressed(work / "arrays.npz", **arrays, halves=np.stack(vols))


def _seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=("make", "run", "halves", "table"))
    p.add_argument("--families", default=",".join(FAMILIES))
    p.add_argument("--seeds", default="0-7", help="e.g. 0-7 or 0,2,5")
    p.add_argument("--replicates", type=int, default=2)
    p.add_argument("--write", action="store_true", help="table: also write benchmarks/results/error_bounds_table_cpu.json")
    args = p.parse_args()
    if args.what == "table":
        from benchmarks._error_bounds_table import main as table

        return table(["--write"] if args.write else [])
    for seed in _seeds(args.seeds):
        for family in args.families.split(","):
            t0 = time.perf_counter()
            if args.what == "make":
                make(family, seed)
                print(f"{scene_name(family, seed)}: made in {time.perf_counter() - t0:.0f} s", flush=True)
            elif args.what == "halves":
                halves(family, seed)
                print(f"{scene_name(family, seed)}: halves in {time.perf_counter() - t0:.0f} s", flush=True)
            else:
                row = run(family, seed, args.replicates)
                print(f"{row['scene']}: error {row['relative_error']:.3f}, tv {row['tv_xy_weight']}, parts {row['parts']}, "
                      f"run {row['run_s']} s, replicates {row['replicates_s']} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
