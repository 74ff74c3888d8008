"""Probe (issue 24, a kept part): can the model parts be chosen before the coarse stages, from a Δn = 0 pilot?

    python -m benchmarks run parts_pilot_probe ACQ_DIR [--iterations 80] [--seed 0]

The finest stage's model with the volume held at zero (RI step 0): the sources, the depth offset and the gains trained
through the homogeneous medium for ``--iterations`` steps; then each "auto" part's paired test of the solver
(:func:`napari_fdt.recon.model_parts.decide` on the held-out images; the pupil and aberrations fitted as at the
finest stage's end, :func:`napari_fdt.recon.parts_search.fit_pupil_parts`). If the test found a part here, the
coarse stages could run with it from the start and a kept part would cost no second pass. Appends one row per scene to
``benchmarks/results/parts_pilot_probe_cpu.jsonl``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from benchmarks._results import append_row, results_file
from napari_fdt.data.io import read_acquisition
from napari_fdt.recon import parts_search as ps
from napari_fdt.recon.config import SolverConfig
from napari_fdt.recon.model_parts import decide
from napari_fdt.recon.parts_switch import set_parts
from napari_fdt.recon.solver import Reconstructor


def _z(verdict: dict) -> float:
    return verdict["improvement"] / max(verdict["standard_error"], 1e-12)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("acquisition")
    ap.add_argument("--iterations", type=int, default=80)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--subset", action="store_true", help="train only the fit images and the held-out images")
    ap.add_argument("--subset-batch", type=int, default=8, help="images of each kind per iteration with --subset")
    ap.add_argument("--exact-zero", action="store_true", help="Δn exactly 0 instead of the activation's floor (1e-4)")
    a = ap.parse_args()
    acq = read_acquisition(a.acquisition)
    cfg = SolverConfig.from_dict({**SolverConfig().to_dict(), "tv_xy_weight": 1.0, "tv_z_weight": 0.5, "seed": a.seed,
                                  "stages": [{"factor": 1, "iterations": 1000, "batch_size": None}],
                                  "final_stage_min_passes": 0, "early_stopping": "off", "calibration_from_stage": 0,
                                  # with --subset only the held-out images' positions are fitted: they alone are the test
                                  **({"parts_test_images": "held_out"} if a.subset else {})})
    rec = Reconstructor(acq, cfg, device="cpu")
    stage = rec._build_stage(0)
    rec._carry_volume_to(stage)
    mask = rec._loss_mask(stage)
    rec._init_gains(stage, mask)
    rec.calibration.set_trainable(0)
    frozen = torch.optim.Adam([rec.volume.x], lr=0.0)
    if a.exact_zero:  # Δn exactly 0 (the split-field model then skips its slice loop), not the activation's floor
        shape = tuple(rec.volume.x.shape)
        rec.volume.delta_n = lambda: torch.zeros(shape, device=rec.device, dtype=rec.volume.x.dtype)
    t0 = time.perf_counter()
    start_err = ps.choice_errors(rec, stage, mask)[0]
    if a.subset:  # only the images the test reads: the pupil fit's images and the held-out ones
        from napari_fdt.recon.losses import total_loss
        held = torch.as_tensor(rec.validation_indices, device=rec.device)
        fit = ps.fit_images(rec)
        rng = np.random.default_rng(a.seed)
        cal = rec.calibration
        zero = rec.volume.delta_n().detach()
        for it in range(a.iterations):
            f = fit[torch.as_tensor(rng.permutation(len(fit))[: a.subset_batch], device=rec.device)]
            h = held[torch.as_tensor(rng.permutation(len(held))[: a.subset_batch], device=rec.device)]
            pred = torch.cat([rec._predict_normalised(stage, zero, f), rec._predict_normalised(stage, zero, h, held_out=True)])
            idx = torch.cat([f, h])
            loss, _ = total_loss(pred, stage.images[idx], zero, rec.loss_weights, 0.5, mask=None if mask is None else mask[idx],
                                 data_range=float(stage.images.max()))
            cal.optimiser.zero_grad(set_to_none=True)
            loss.backward()
            cal.optimiser.step()
    else:
        for _ in range(a.iterations):
            rec._step(stage, mask, frozen, cfg.batch_size, 1.0, 0.5)
    pilot_s = time.perf_counter() - t0
    ref_err, ref_each = ps.choice_errors(rec, stage, mask)
    row = {"scene": a.acquisition, "seed": a.seed, "iterations": a.iterations, "exact_zero": a.exact_zero, "subset": a.subset, "pilot_s": pilot_s,
           "held_out_error_start": start_err, "held_out_error": ref_err, "parts": {}}
    print(f"{a.acquisition}: pilot {a.iterations} it, {pilot_s:.1f} s; held-out error {start_err:.4f} -> {ref_err:.4f}")
    for part in [p for p in ("pixel_integration", "obliquity", "spectral") if p in rec._auto_parts]:
        set_parts(rec, {**rec.parts, part: True})
        variant = stage if part == "spectral" else rec._build_stage(0)
        err, each = ps.choice_errors(rec, variant, rec._loss_mask(variant))
        v = decide(np.asarray(ref_each), each)
        row["parts"][part] = {"error": err, "z": _z(v), "on": v["on"]}
        set_parts(rec, {**rec.parts, part: False})
    for part in [p for p in ("pupil", "aberrations") if p in rec._auto_parts]:
        values = rec.calibration.copy_values()
        set_parts(rec, {**rec.parts, part: True})
        variant = rec._build_stage(0)
        ps.fit_pupil_parts(rec, variant, ps.exit_cache(rec, variant), [part], None)
        err, each = ps.choice_errors(rec, variant, rec._loss_mask(variant))
        v = decide(np.asarray(ref_each), each)
        row["parts"][part] = {"error": err, "z": _z(v), "on": v["on"], "fitted": ps.pupil_values(rec, [part])}
        rec.calibration.restore_values(values)
        set_parts(rec, {**rec.parts, part: False})
    for part, r in row["parts"].items():
        print(f"  {part}: held-out error {r['error']:.4f} ({100 * (r['error'] / ref_err - 1):+.1f} %), z {r['z']:.2f}, kept {r['on']}")
    append_row(results_file("parts_pilot_probe", "cpu"), row, "cpu")


if __name__ == "__main__":
    main()
