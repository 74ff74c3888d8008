"""Issue 27 probe (deleted after its run; record: docs/decisions/model-parts.md, "Forward-accuracy parts"): at the
finest stage's end of a run with one screen per slice and the other parts off, the parts' paired test of the 2x field
grid, its RI taken from the camera-grid volume by linear interpolation (the model's) or by Fourier interpolation.

    python -m benchmarks run field_grid_probe SCENE_DIR SEED       # one JSON line to stdout, one row to results
"""

from __future__ import annotations

import dataclasses
import json
import sys

import torch

import napari_fdt.model.oversampled as oversampled
from benchmarks._results import append_row, results_file
from napari_fdt.data.io import read_acquisition
from napari_fdt.recon.config import SolverConfig
from napari_fdt.recon.model_parts import decide
from napari_fdt.recon.parts_search import choice_errors
from napari_fdt.recon.solver import Reconstructor


def fourier_upsample(dn: torch.Tensor) -> torch.Tensor:
    """(..., H, W) → (..., 2H, 2W) by zero-padding the spectrum (after a margin of half the image of zero contrast);
    the even fine points keep the coarse values."""
    h0, w0 = dn.shape[-2:]
    ph, pw = h0 // 2, w0 // 2
    x = torch.nn.functional.pad(dn, (pw, pw, ph, ph))
    h, w = x.shape[-2:]
    spec = torch.fft.fftshift(torch.fft.fft2(x), dim=(-2, -1))
    big = torch.zeros(x.shape[:-2] + (2 * h, 2 * w), dtype=spec.dtype, device=spec.device)
    big[..., h // 2: h // 2 + h, w // 2: w // 2 + w] = spec
    y = torch.fft.ifft2(torch.fft.ifftshift(big, dim=(-2, -1))).real * 4
    return y[..., 2 * ph: 2 * ph + 2 * h0, 2 * pw: 2 * pw + 2 * w0]


def main(argv: list[str] | None = None) -> int:
    scene, seed = (argv or sys.argv[1:])[:2]
    cfg = SolverConfig(seed=int(seed), sub_slices=1, field_oversampling=1, coherence="none", calibrate_pupil="false",
                       calibrate_aberrations="false", obliquity_correction="false")
    rec = Reconstructor(read_acquisition(scene), cfg, device="cpu")
    for _ in rec.run():
        pass
    stage = rec._build_stage(2)
    ref, ref_each = choice_errors(rec, stage, rec._loss_mask(stage))
    row = {"scene": scene, "seed": int(seed), "reference_error": ref}
    rec.config = dataclasses.replace(cfg, field_oversampling=2)
    linear = oversampled.upsample_volume
    for name, upsample in (("linear", linear), ("fourier", fourier_upsample)):
        oversampled.upsample_volume = upsample
        fine = rec._build_stage(2)
        _, each = choice_errors(rec, fine, rec._loss_mask(fine))
        v = decide(ref_each, each)
        row[name] = {"relative_change": -v["improvement"] / ref, "z": v["improvement"] / v["standard_error"], "on": v["on"]}
    oversampled.upsample_volume = linear
    append_row(results_file("field_grid_probe", "cpu"), row, "cpu")
    print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
