"""Ablation table in the shape of the paper's Table S1: each component on and off, measured.

Usage (repository root)::

    python -m benchmarks run ablation [--device cpu] [--out docs/ablation.md]

Datasets (all the bundled sample's geometry: 96×96 px of 0.33 µm, 8 slices of 2 µm, 64 sources 40 µm deep,
NA 0.8, noise 2000 photo-electrons, brightness spread 0.2, initial positions jittered 1 µm per axis):

* ``coherent``: the bundled ``sample_data/letters``;
* ``partially coherent``: the same scene simulated with a 40 nm (FWHM) emission band in 9 wavelengths
  (``fdt simulate letters … --bandwidth-um 0.04``), reconstructed with each coherence model;
* ``pixel size 2 % off``: the bundled sample with ``pixel_size_um`` written as 0.3366 instead of 0.33,
  reconstructed with and without self-calibration of the pixel size.

Every row is a full reconstruction with the default settings except the one named change. Writes a JSON
file of all numbers beside the Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from benchmarks._results import write_document
from napari_fdt import read_acquisition, read_volume_tiff, simulate, source_grid
from napari_fdt.recon.assess.metrics import ri_metrics
from napari_fdt.recon.run.report import evaluate_images, source_errors
from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.config import SolverConfig, StageConfig
from napari_fdt.sim.phantoms import text_phantom

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data" / "letters"


def run(acq, truth_ri, truth_src, config: SolverConfig, device: str) -> dict:
    rec = Reconstructor(acq, config, device=device)
    t0 = time.perf_counter()
    for _ in rec.run():
        pass
    wall = time.perf_counter() - t0
    m = ri_metrics(rec.ri_full(), truth_ri, acq.optics.n_background)
    _, fit = evaluate_images(rec)
    src = source_errors(rec.sources_um(), truth_src)
    return {
        "relative_delta_n_error": m["relative_delta_n_error"], "ri_rmse": m["ri_rmse"],
        "paper_psnr": m["paper_normalised"]["psnr"], "paper_ssim": m["paper_normalised"]["ssim"],
        "image_relative_error": fit["image_relative_error"], "image_ssim": fit["image_ssim"],
        "source_lateral_rms_um": src["lateral_rms_um"], "wall_s": wall,
        "iterations": config.total_iterations, "calibration": rec.calibration.summary(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "ablation.md")
    args = parser.parse_args()

    acq = read_acquisition(SAMPLE)
    truth, _ = read_volume_tiff(SAMPLE / "ground_truth_ri.tif")
    truth_src = np.array(json.loads((SAMPLE / "ground_truth_sources_um.json").read_text())["sources_um"])
    base = SolverConfig()
    one_stage = [StageConfig(1, base.total_iterations)]
    rows = []

    def add(dataset: str, name: str, acq_, cfg: SolverConfig) -> None:
        r = run(acq_, truth, truth_src, cfg, args.device)
        r.update(dataset=dataset, row=name)
        rows.append(r)
        print(f"{dataset:20s} {name:38s} err {r['relative_delta_n_error']:.3f}  PSNR {r['paper_psnr']:.1f}  SSIM {r['paper_ssim']:.3f}  "
              f"src {r['source_lateral_rms_um']:.3f} µm  {r['wall_s']:.0f} s", flush=True)

    c = "coherent"
    add(c, "full (defaults)", acq, base)
    add(c, "without coarse-to-fine (1 stage, same iterations)", acq, dataclasses.replace(base, stages=one_stage, calibration_from_stage=0))
    add(c, "without coarse-to-fine (1 stage, about the same time)", acq,
        dataclasses.replace(base, stages=[StageConfig(1, 200)], calibration_from_stage=0))
    add(c, "coarse stages with the multi-slice model (not envelopes)", acq, dataclasses.replace(base, coarse_model="multislice"))
    add(c, "without source-position calibration", acq, dataclasses.replace(base, calibrate_sources=False))
    add(c, "without source-depth calibration", acq, dataclasses.replace(base, calibrate_source_depth=False))
    add(c, "without any self-calibration (gain fixed at its LS start)", acq,
        dataclasses.replace(base, calibrate_sources=False, calibrate_source_depth=False, calibrate_gain=False))
    add(c, "with TV (xy 1e-3, z 1e-3)", acq, dataclasses.replace(base, tv_xy_weight=1e-3, tv_z_weight=1e-3))
    add(c, "with SSIM loss (weight 0.1)", acq, dataclasses.replace(base, ssim_weight=0.1))

    o = acq.optics
    wrong = dataclasses.replace(acq, optics=dataclasses.replace(o, pixel_size_um=o.pixel_size_um * 1.02))
    p = "pixel size 2 % off"
    add(p, "without pixel-size calibration", wrong, base)
    add(p, "with pixel-size calibration", wrong, dataclasses.replace(base, calibrate_pixel_size=True, lr_global=2e-3))

    meta = json.loads((SAMPLE / "acquisition.json").read_text())["simulated"]
    dn = text_phantom(acq.image_shape, o.n_slices, text="UCDAVIS", delta_n=0.05)
    span = 0.8 * min(acq.image_shape) * o.pixel_size_um
    sim = simulate(dn, o, source_grid(8, span, 40.0), seed=0, device=args.device, bandwidth_um=0.04, n_wavelengths=9,
                   photons=meta["photons"], read_noise=meta["read_noise"], brightness_spread=meta["brightness_spread"])
    pc_acq = sim.acquisition
    pc_truth_src = sim.sources_um
    assert np.allclose(pc_truth_src, truth_src)
    q = "partially coherent"
    add(q, "coherent model (no mask)", pc_acq, base)
    add(q, "paper's masks", pc_acq, dataclasses.replace(base, coherence="mask"))
    add(q, "spectral model (3 wavelengths, 40 nm)", pc_acq, dataclasses.replace(base, coherence="spectral", bandwidth_um=0.04, n_wavelengths=3))
    add(q, "masks + spectral model", pc_acq, dataclasses.replace(base, coherence="mask+spectral", bandwidth_um=0.04, n_wavelengths=3))

    hardware = json.loads(write_document(args.out.with_suffix(".json"), {"rows": rows}, args.device).read_text())["hardware"]
    lines = [
        "| data | configuration | relative Δn error | RI RMSE | norm. PSNR (dB) | norm. SSIM | image rel. error | source RMS (µm) | wall time (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['dataset']} | {r['row']} | {r['relative_delta_n_error']:.3f} | {r['ri_rmse']:.2e} | {r['paper_psnr']:.1f} | "
                     f"{r['paper_ssim']:.3f} | {r['image_relative_error']:.4f} | {r['source_lateral_rms_um']:.3f} | {r['wall_s']:.0f} |")
    table = "\n".join(lines)
    print(table)
    import datetime

    page = [
        "# Ablation: each component on and off",
        "",
        "Made by `python -m benchmarks run ablation --device cpu` (this page and `ablation.json`, which holds every number",
        f"and the calibrated parameters). Run on {datetime.date.today().isoformat()}: {hardware['threads']} CPU threads,",
        f"torch {hardware['torch']}, the project's 2-core CI-class machine. The shape follows the paper's Table S1.",
        "",
        "Data: the bundled sample's geometry (96×96 px of 0.33 µm, 8 slices of 2 µm holding the letters U, C, D, A",
        "at Δn 0.05, 64 sources 40 µm deep, NA 0.8, 2000 photo-electrons per pixel, brightness spread 0.2, initial",
        "positions jittered by 1 µm per axis). *coherent*: the bundled sample itself. *pixel size 2 % off*: the same",
        "images with `pixel_size_um` given as 0.3366. *partially coherent*: the same scene simulated with a 40 nm",
        "emission band (9 wavelengths). Every row is a full run with the default settings except the named change.",
        "Metrics: relative Δn error ‖Δn − Δn_true‖/‖Δn_true‖; RI RMSE in absolute RI; the paper code's normalised",
        "PSNR/SSIM; the relative error of all 64 predicted images against the measured ones (noise level 0.020);",
        "the RMS lateral error of the calibrated source positions. Wall time includes set-up, not the evaluation.",
        "",
        table,
        "",
    ]
    args.out.write_text("\n".join(page))


if __name__ == "__main__":
    main()
