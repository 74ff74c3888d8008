"""The slice loop with FFTs as DFT-matrix products (:mod:`benchmarks._dft_loop`) against torch.fft (issue 16, item 2).

    OMP_NUM_THREADS=1 python -m benchmarks run dft_loop_speed --device cpu --sizes 128,256,512 --batch 8 --slices 14
    python -m benchmarks run dft_loop_speed --device cuda --sizes 512,1024 --batch 30 --slices 14,24     # a GPU session

Per size: one 2D transform pair (forward + unnormalised inverse) of a batch of complex64 fields, and one step of
the slice loop (forward, |u|² loss, backward to v0, φ and K): the package's ``slice_loop`` (stored mode, torch.fft)
against ``dft_slice_loop`` (plain autograd through the matrix products). Medians of ``--repeats`` after one warm-up.
Writes ``benchmarks/results/dft_loop_<device>.json``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from benchmarks._dft_loop import DftPlan, dft_slice_loop
from benchmarks._results import results_file, write_document
from napari_fdt import resolve_device
from napari_fdt.model.slice_loop import slice_loop
from napari_fdt.physics.propagation import propagation_kernel

ROOT = Path(__file__).resolve().parents[1]


def _time(fn, device, repeats):
    fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--sizes", default="128,256,512")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--slices", default="14", help="one count, or one per size")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    device = resolve_device(args.device)
    sizes = [int(s) for s in args.sizes.split(",")]
    slices = [int(s) for s in args.slices.split(",")]
    slices = slices * len(sizes) if len(slices) == 1 else slices
    rows = []
    for n, n_slices in zip(sizes, slices):
        gen = torch.Generator().manual_seed(0)
        plan = DftPlan((n, n), dtype=torch.complex64, device=device)
        u = torch.randn(args.batch, n, n, generator=gen, dtype=torch.complex64).to(device)
        f = torch.fft.fftfreq(n, 0.33, dtype=torch.float64)
        kernel = propagation_kernel(f[:, None] ** 2 + f[None, :] ** 2, 1.5, 1.33, 0.6).to(torch.complex64).to(device)
        phi = (0.5 * torch.rand(n_slices, n, n, generator=gen)).to(device)
        t_fft_pair = _time(lambda: torch.fft.ifft2(torch.fft.fft2(u), norm="forward"), device, args.repeats)
        t_dft_pair = _time(lambda: plan.ifft2(plan.fft2(u)), device, args.repeats)

        def step(loop):
            v0 = u.clone().requires_grad_()
            ph = phi.clone().requires_grad_()
            k = kernel.clone().requires_grad_()
            out = loop(v0, ph, k)
            (out.real.square() + out.imag.square()).mean().backward()

        t_fft_loop = _time(lambda: step(lambda v, ph, k: slice_loop(v, ph, k, "stored")), device, args.repeats)
        t_dft_loop = _time(lambda: step(lambda v, ph, k: dft_slice_loop(v, ph, k, plan)), device, args.repeats)
        row = {"size": n, "factors": [plan.h.n1, plan.h.n2], "batch": args.batch, "slices": n_slices,
               "fft_pair_ms": 1e3 * t_fft_pair, "dft_pair_ms": 1e3 * t_dft_pair,
               "fft_loop_step_ms": 1e3 * t_fft_loop, "dft_loop_step_ms": 1e3 * t_dft_loop}
        rows.append(row)
        print(f"{n}² ({plan.h.n1}·{plan.h.n2}) ×{args.batch}, {n_slices} slices: transform pair FFT {row['fft_pair_ms']:.1f} ms, "
              f"DFT products {row['dft_pair_ms']:.1f} ms ({t_dft_pair / t_fft_pair:.1f}×); loop step FFT "
              f"{row['fft_loop_step_ms']:.0f} ms, DFT {row['dft_loop_step_ms']:.0f} ms ({t_dft_loop / t_fft_loop:.1f}×)", flush=True)
    out = write_document(args.out or results_file("dft_loop", device, table=False), {"rows": rows}, device)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
