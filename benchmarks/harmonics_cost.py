"""Cost of the exact homogeneous field with non-radial aberrations (angular harmonics) on the sample's geometry.

    python -m benchmarks run harmonics_cost [--threads 1]

Hard pupil, pixel integration, 0.1 rad in each of the six Zernike modes (trainable), 4 images of
``sample_data/letters``: the time of a forward pass on the first call (Bessel tables J_0 … J_M built) and on the
second (tables cached), and of the backward pass. Prints the harmonic order and table shape.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from napari_fdt import read_acquisition
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.grid import plan_for_sources

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    acq = read_acquisition(ROOT / "sample_data" / "letters")
    o = acq.optics
    src = torch.tensor(acq.sources_um[:4], dtype=torch.float32)
    plan = plan_for_sources(o, acq.image_shape, acq.sources_um, warn=False)
    m = MultiSliceModel(o, plan, device="cpu", pupil_edge=0.0, pixel_integration=True)
    dn = torch.zeros((o.n_slices, *acq.image_shape), requires_grad=True)
    z = torch.full((6,), 0.1, requires_grad=True)
    for call in ("first", "second"):
        t0 = time.perf_counter()
        img = m(dn, src, zernike=z)
        t1 = time.perf_counter()
        img.sum().backward()
        t2 = time.perf_counter()
        print(f"{call} call: forward {t1 - t0:.2f} s, backward {t2 - t1:.2f} s")
    key = next((k for k in m._bessel_cache if k and k[0] == "harmonics"), None)
    if key is not None:
        tables = m._bessel_cache[key]
        print(f"tables J_0 … J_{len(tables) - 1} of {tuple(tables[0][1].shape)}, window {plan.padded_shape}, {args.threads} thread(s)")


if __name__ == "__main__":
    main()
