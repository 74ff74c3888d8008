"""The camera and objective parts of the forward model: accuracy against the brute-force reference, and cost.

    python -m benchmarks run optics_parts [--images 4] [--grow 5]

Scene: ``fdt simulate beads``'s defaults (96×96 px of 0.33 µm, NA 0.8, λ 0.635, 8 slices of 2 µm, sources 40 µm
deep on the 8×8 grid spanning 80 % of the field); a subset of the sources (corners and centre first).
Truth: ``tests/independent_reference_optics.py`` (hard pupil on a window ``grow``× the plan, 0.5 rad of primary
spherical aberration, pixel averaging by 4×4 Gauss–Legendre points). Reported: the median over images of the
relative L2 image error, for the model with all parts on and with today's defaults (soft 3 % edge, point
samples, no aberration); then the time of one float32 forward pass of 16 images with each part on (CPU).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from napari_fdt.model.forward import MultiSliceModel  # noqa: E402
from napari_fdt.physics.grid import plan_for_sources  # noqa: E402
from napari_fdt.physics.optics import Optics  # noqa: E402
from napari_fdt.sim.simulate import make_scene, source_grid  # noqa: E402
from tests import independent_reference_optics as ref  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--images", type=int, default=4)
    ap.add_argument("--grow", type=float, default=5.0)
    ap.add_argument("--timing-batch", type=int, default=16)
    args = ap.parse_args()
    torch.set_num_threads(max(1, torch.get_num_threads()))
    opt = Optics(**Optics.examples())
    shape = (96, 96)
    dn = make_scene("beads", shape, opt, rng=0)
    grid = source_grid(8, 0.8 * 96 * opt.pixel_size_um, 40.0)
    order = [0, 63, 7, 56, 27, 36, 9, 54]
    src = grid[order[: args.images]]
    plan = plan_for_sources(opt, shape, grid, warn=False)
    ab = {"spherical": 0.5}
    truth = ref.forward_images_optics(opt.to_dict(), opt.n_background + dn, src, np.ones(len(src)), pupil_edge=0.0,
                                      aberrations=ab, pixel_integration=True, grow=args.grow)
    for label, kw in (("all parts on", dict(pupil_edge=0.0, aberrations=ab, pixel_integration=True)),
                      ("defaults (3 % soft edge, point samples, no aberration)", {})):
        for dtype in (torch.float64, torch.float32):
            m = MultiSliceModel(opt, plan, device="cpu", dtype=dtype, **kw)
            ours = m(torch.tensor(dn), torch.tensor(src)).double().numpy()
            err = [np.linalg.norm(a - b) / np.linalg.norm(b) for a, b in zip(ours, truth)]
            print(f"{label}, {str(dtype)[6:]}: median image error {100 * np.median(err):.2f} % (max {100 * max(err):.2f} %)")
    src16 = torch.tensor(grid[: args.timing_batch])
    d = torch.tensor(dn, dtype=torch.float32)
    base_t = None
    for label, kw in (("defaults", {}), ("pixel integration", dict(pixel_integration=True)),
                      ("hard pupil (exact homogeneous field)", dict(pupil_edge=0.0)),
                      ("Zernike phase", dict(aberrations=ab)),
                      ("all three", dict(pupil_edge=0.0, aberrations=ab, pixel_integration=True))):
        m = MultiSliceModel(opt, plan, device="cpu", **kw)
        with torch.no_grad():
            m(d, src16)
            t0 = time.perf_counter()
            for _ in range(2):
                m(d, src16)
            t = (time.perf_counter() - t0) / 2
        base_t = base_t or t
        print(f"forward of {args.timing_batch} images, window {plan.padded_shape}: {label}: {t:.2f} s ({t / base_t:.2f}×)")


if __name__ == "__main__":
    main()
