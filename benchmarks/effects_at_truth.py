"""The forward model at the truth on a model-parts scene (docs/solver.md, "Model parts"): does the solver's model, with
its own window, reproduce the simulated images; how much does a 0.004 or 0.03 pupil edge change them; and is a common
source-depth shift degenerate with the defocus and spherical aberration (the true volume held, the two modes refitted)?

Usage (repository root; scenes of ``benchmarks/model_parts.py make-scenes``)::

    python -m benchmarks run effects_at_truth out/parts/letters_effects

Errors: median over images of the relative L2 error after a least-squares gain per image.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import torch

from napari_fdt import read_acquisition, read_volume_tiff
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.render import render_images
from napari_fdt.physics.aberrations import ZERNIKE_MODES
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.recon.stages import multislice_plan

ABERRATIONS = {"spherical": 0.5}  # what model_parts.py's _effects scenes hold


def relative_error(pred: np.ndarray, ref: np.ndarray) -> float:
    """Median over images (N, H, W) of ‖g·pred − ref‖/‖ref‖ with the least-squares gain g of each image."""
    pred, ref = np.asarray(pred, np.float64), np.asarray(ref, np.float64)
    g = (pred * ref).sum((1, 2)) / (pred * pred).sum((1, 2))
    e = np.linalg.norm((g[:, None, None] * pred - ref).reshape(len(ref), -1), axis=1)
    return float(np.median(e / np.linalg.norm(ref.reshape(len(ref), -1), axis=1)))


def main(folder: str) -> None:
    torch.set_num_threads(1)
    acq = read_acquisition(folder)
    o = acq.optics
    truth, _ = read_volume_tiff(f"{folder}/ground_truth_ri.tif")
    dn = truth - o.n_background
    src = np.array(json.loads(open(f"{folder}/ground_truth_sources_um.json").read())["sources_um"])
    sim_plan = plan_for_sources(o, acq.image_shape, src, warn=False)
    _, _, _, solver_plan = multislice_plan(o, 1, acq.image_shape, acq.sources_um)
    print(f"windows: simulator {sim_plan.padded_shape}, solver {solver_plan.padded_shape}")

    def images(plan, **kw):
        m = MultiSliceModel(o, plan, device="cpu", aberrations=ABERRATIONS, pixel_integration=True, **kw)
        return render_images(m, dn, src, batch_size=16)

    data = acq.images.astype(np.float64)
    ref = images(sim_plan, pupil_edge=0.0)
    print(f"data against the simulator's clean images (the noise): {relative_error(ref, data):.4f}")
    for name, plan, edge in [("solver window, hard pupil", solver_plan, 0.0), ("solver window, edge 0.004", solver_plan, 0.004),
                             ("solver window, edge 0.03", solver_plan, 0.03)]:
        pred = images(plan, pupil_edge=edge)
        print(f"{name}: against the clean images {relative_error(pred, ref):.4f}, against the data {relative_error(pred, data):.4f}")

    # a common depth shift of the sources against the defocus + spherical refit (16 images, the true volume)
    idx = np.arange(0, len(src), 4)
    m = MultiSliceModel(o, sim_plan, device="cpu", pupil_edge=0.0, pixel_integration=True, aberrations=ABERRATIONS)
    meas = torch.tensor(acq.images[idx].astype(np.float32))
    modes = torch.tensor([ZERNIKE_MODES.index("defocus"), ZERNIKE_MODES.index("spherical")])
    dn_t = torch.tensor(dn)
    for shift in (0.0, 0.2, 0.4, -0.4):
        s = torch.tensor(src[idx], dtype=torch.float32)
        s[:, 2] += shift
        with torch.no_grad():
            exit_spec, spec0 = m.exit_spectra(dn_t, s)
        c = torch.tensor([0.0, ABERRATIONS["spherical"]], requires_grad=True)
        opt = torch.optim.Adam([c], lr=0.02)
        for _ in range(60):
            z = torch.zeros(len(ZERNIKE_MODES)).index_put((modes,), c)
            pred = m.intensity_from_exit(exit_spec, spec0, s, zernike=z)
            g = ((pred * meas).sum((1, 2)) / (pred * pred).sum((1, 2))).detach()
            loss = (g[:, None, None] * pred - meas).square().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            fitted = m.intensity_from_exit(exit_spec, spec0, s, zernike=torch.zeros(len(ZERNIKE_MODES)).index_put((modes,), c))
        print(f"sources {shift:+.1f} µm deeper: defocus, spherical refitted {c.detach().numpy().round(3)} rad → "
              f"{relative_error(fitted.numpy(), meas.numpy()):.4f}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1])
