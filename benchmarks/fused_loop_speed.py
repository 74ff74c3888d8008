"""The fused Triton slice loop (:mod:`napari_fdt.model.fused_loop`) against the FFT loop on a GPU (issue 16, item 2).

    python -m benchmarks run fused_loop_speed --sizes 512,1024 --slices 14,24 --batch 30        # a GPU session
    python -m benchmarks run fused_loop_speed --device cpu --sizes 64 --slices 4 --batch 2 --repeats 1   # interpreter

One step of the slice loop (forward, weighted |u|² loss, backward to v0 and φ) per size: the package's
``slice_loop`` in ``"stored"`` mode (torch.fft, cuFFT on a GPU) against ``fused_slice_loop`` in each precision
("ieee": float32 products on the CUDA cores; "tf32x3": tensor cores at about float32 accuracy). The issue's
targets are ≤ 7 ms at 512²×14×B30 and ≤ 40 ms at 1024²×24×B30 for the whole step. Also prints the relative
difference of the gradients from the FFT loop (float32 both). On the CPU the kernels run in Triton's interpreter
(numpy): its times say nothing about a GPU. Medians of ``--repeats`` after one warm-up (which includes Triton's
compilation, reported separately as ``first_ms``). Writes ``benchmarks/results/fused_loop_<device>.json``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from benchmarks._results import results_file, write_document
from napari_fdt import resolve_device
from napari_fdt.model.fused_loop import PRECISIONS, fused_slice_loop, supports
from napari_fdt.model.slice_loop import slice_loop
from napari_fdt.physics.propagation import propagation_kernel

ROOT = Path(__file__).resolve().parents[1]


def _sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time(fn, device, repeats):
    _sync(device)
    t0 = time.perf_counter()
    fn()
    _sync(device)
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda")
    p.add_argument("--sizes", default="512,1024")
    p.add_argument("--batch", type=int, default=30)
    p.add_argument("--slices", default="14,24", help="one count, or one per size")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    device = resolve_device(args.device)
    interpret = device.type == "cpu"
    sizes = [int(s) for s in args.sizes.split(",")]
    slices = [int(s) for s in args.slices.split(",")]
    slices = slices * len(sizes) if len(slices) == 1 else slices
    rows = []
    for n, n_slices in zip(sizes, slices):
        ok, why = supports((n, n), device, interpret=interpret)
        if not ok:
            print(f"{n}²: skipped ({why})")
            continue
        gen = torch.Generator().manual_seed(0)
        v0 = torch.randn(args.batch, n, n, generator=gen, dtype=torch.complex64).to(device)
        f = torch.fft.fftfreq(n, 0.33, dtype=torch.float64)
        kernel = propagation_kernel(f[:, None] ** 2 + f[None, :] ** 2, 1.5, 1.33, 0.6).to(torch.complex64).to(device)
        phi = (0.5 * torch.rand(n_slices, n, n, generator=gen)).to(device)
        weight = torch.rand(args.batch, n, n, generator=gen).to(device)

        def step(loop):
            a = v0.clone().requires_grad_()
            ph = phi.clone().requires_grad_()
            u = loop(a, ph)
            ((u.real.square() + u.imag.square()) * weight).sum().backward()
            return a.grad, ph.grad

        ref_grads = step(lambda a, ph: slice_loop(a, ph, kernel, "stored"))
        first, t_fft = _time(lambda: step(lambda a, ph: slice_loop(a, ph, kernel, "stored")), device, args.repeats)
        row = {"size": n, "batch": args.batch, "slices": n_slices, "fft_loop_step_ms": 1e3 * t_fft}
        line = f"{n}² ×{args.batch}, {n_slices} slices: FFT loop {1e3 * t_fft:.2f} ms"
        for precision in PRECISIONS:
            def fused(a, ph, precision=precision):
                return fused_slice_loop(a, ph, kernel, interpret=interpret, precision=precision)

            grads = step(fused)
            diff = max(float((g - r).norm() / r.norm()) for g, r in zip(grads, ref_grads))
            first, t = _time(lambda: step(fused), device, args.repeats)
            row[f"fused_{precision}_step_ms"] = 1e3 * t
            row[f"fused_{precision}_first_ms"] = 1e3 * first
            row[f"fused_{precision}_grad_rel_diff"] = diff
            line += f"; fused {precision} {1e3 * t:.2f} ms ({t / t_fft:.2f}×, gradients {diff:.1e} from the FFT loop)"
        rows.append(row)
        print(line, flush=True)
    meta = {"interpreter": interpret}
    try:
        import triton

        meta["triton"] = triton.__version__
    except ImportError:
        pass
    out = write_document(args.out or results_file("fused_loop", device, table=False), {"hardware": meta, "rows": rows}, device)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
