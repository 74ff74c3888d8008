"""Peak memory of the forward model without autograd (``fdt forward``, ``fdt simulate``), per window pixel.

Run from the repository root::

    python -m benchmarks run forward_memory            # CPU (one subprocess per configuration), and CUDA if present

For each (window side, slices, batch) it builds a :class:`~napari_fdt.model.forward.MultiSliceModel` on a window of
that size, renders ``batch`` images with :func:`napari_fdt.model.render.render_images` (``torch.no_grad``) and
records the peak memory above what was held before the call: on CUDA ``torch.cuda.max_memory_allocated``, on
CPU the growth of the process's peak resident set (``VmHWM``) in a fresh subprocess. It prints the fit
``bytes ≈ a·P·batch + b·P·n_slices`` (P = window pixels) that ``napari_fdt.model.memory.forward_bytes`` uses.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CONFIGS = [(1024, 4, 1), (1024, 4, 8), (1024, 4, 16), (1024, 32, 1), (1024, 32, 8), (2048, 8, 4), (2048, 8, 8)]


def measure(side: int, n_slices: int, batch: int, device: str) -> int:
    import resource
    import warnings

    import numpy as np
    import torch

    from napari_fdt.model.forward import MultiSliceModel
    from napari_fdt.model.render import render_images
    from napari_fdt.physics.grid import GridPlan
    from napari_fdt.physics.optics import Optics

    warnings.simplefilter("ignore")
    torch.set_num_threads(2)
    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=n_slices, slice_spacing_um=2.0)
    h = side // 2
    plan = GridPlan((h, h), (side, side), (side // 2 - h // 2,) * 2, 0.33, 0.03, 1.3, 1.5, 5.0)
    model = MultiSliceModel(o, plan, device=device)
    dn = np.zeros((n_slices, h, h), np.float32)
    src = np.tile([[0.0, 0.0, 40.0]], (batch, 1))
    if device == "cuda":
        torch.cuda.synchronize()
        before = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
        render_images(model, dn, src, batch_size=batch)
        torch.cuda.synchronize()
        return int(torch.cuda.max_memory_allocated() - before)
    small = GridPlan((32, 32), (64, 64), (16, 16), 0.33, 0.03, 1.3, 1.5, 5.0)
    render_images(MultiSliceModel(o, small, device=device), np.zeros((n_slices, 32, 32), np.float32), src[:1])  # warm-up
    with open("/proc/self/statm") as fh:  # resident pages now
        before = int(fh.read().split()[1]) * resource.getpagesize()
    render_images(model, dn, src, batch_size=batch)
    # This process's own high-water mark. Not ru_maxrss: Linux carries the parent's peak RSS over fork and
    # exec into it, so a child of a large process (pytest after the solver tests) read the parent's peak.
    with open("/proc/self/status") as fh:
        hwm = next(int(line.split()[1]) * 1024 for line in fh if line.startswith("VmHWM:"))
    return int(hwm - before)


def fit(rows: list[tuple[int, int, int, int]]) -> tuple[float, float]:
    """Least squares of bytes = a·P·batch + b·P·n_slices over the rows (side, slices, batch, bytes)."""
    import numpy as np

    A = np.array([[s * s * b, s * s * n] for s, n, b, _ in rows], float)
    y = np.array([r[3] for r in rows], float)
    (a, b), *_ = np.linalg.lstsq(A, y, rcond=None)
    return float(a), float(b)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--one", nargs=3, type=int, metavar=("SIDE", "SLICES", "BATCH"),
                    help="measure one window (CPU) in this process and print its peak bytes (the sweep runs each so)")
    args = ap.parse_args()
    if args.one:
        print(json.dumps(measure(*args.one, "cpu")))
        return 0
    import torch

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for device in devices:
        rows = []
        for side, n, b in CONFIGS:
            if device == "cpu":
                out = subprocess.run([sys.executable, __file__, "--one", str(side), str(n), str(b)],
                                     capture_output=True, text=True, check=True)
                peak = json.loads(out.stdout.strip().splitlines()[-1])
            else:
                peak = measure(side, n, b, device)
            rows.append((side, n, b, peak))
            print(f"{device}: window {side}², {n} slices, batch {b}: {peak / 2**20:.0f} MiB = "
                  f"{peak / (side * side * b):.1f} B per pixel per image", flush=True)
        a, c = fit(rows)
        print(f"{device}: fit {a:.1f} B per window pixel per image + {c:.1f} B per window pixel per slice")
    return 0


if __name__ == "__main__":
    sys.exit(main())
