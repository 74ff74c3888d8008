"""Speed and peak memory of one training step (forward + backward): naive reference against the package.

Usage (repository root)::

    python -m benchmarks run step_speed --device cuda                 # 512²×14 and 1024²×24 at batch 30, 1024²×96 memory
    python -m benchmarks run step_speed --device cpu --quick          # small sizes, to try it without a GPU

For each size, on the same random inputs in one process: the naive eager step
(``benchmarks/naive_step.py``), the package's slice loop in each backward mode
(``napari_fdt.model.slice_loop``), the same with the whole step captured in a CUDA graph, and the full
``MultiSliceModel`` step on the demo geometry's planned window. Times are medians of CUDA-event
(or host-clock on CPU) timings after warm-up; peak memory is ``torch.cuda.max_memory_allocated``
above the inputs. Writes ``benchmarks/results/step_speed_<device>.json`` and prints a Markdown table.
Nothing here is asserted: tests check correctness, this file reports.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

import torch

from benchmarks._results import results_file, write_document  # noqa: E402
from benchmarks.naive_step import naive_step  # noqa: E402
from napari_fdt import MultiSliceModel, Optics, plan_for_sources, resolve_device, source_grid  # noqa: E402
from napari_fdt.model.slice_loop import slice_loop  # noqa: E402
from napari_fdt.physics.grid import frequency_grid  # noqa: E402
from napari_fdt.physics.propagation import propagation_kernel, pupil  # noqa: E402

LAM, NB, NA, DX, DZ = 0.6, 1.33, 0.65, 0.33, 1.5


def _timer(device):
    if device.type == "cuda":
        def run(fn, repeats):
            times = []
            for _ in range(repeats):
                a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                a.record()
                fn()
                b.record()
                b.synchronize()
                times.append(a.elapsed_time(b) / 1e3)
            return times
    else:
        def run(fn, repeats):
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                fn()
                times.append(time.perf_counter() - t0)
            return times
    return run


def _measure(name, fn, device, run, repeats, base_bytes):
    """Warm up, record the peak memory of one call above ``base_bytes``, then time ``repeats`` calls."""
    try:
        fn()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
            torch.cuda.reset_peak_memory_stats(device)
        fn()
        peak = (torch.cuda.max_memory_allocated(device) - base_bytes) / 2**30 if device.type == "cuda" else None
        times = run(fn, repeats)
        return {"variant": name, "median_s": statistics.median(times), "all_s": times, "peak_gib": peak}
    except torch.OutOfMemoryError:
        torch.cuda.empty_cache()
        return {"variant": name, "median_s": None, "error": "out of memory"}


def _inputs(side, n_slices, batch, device, seed=0):
    g = torch.Generator().manual_seed(seed)
    v0 = torch.randn((batch, side, side), generator=g, dtype=torch.complex64).to(device)
    dn = (0.03 * torch.rand((n_slices, side, side), generator=g)).to(device)
    target = torch.rand((batch, side, side), generator=g).to(device)
    fy, fx = frequency_grid((side, side), DX, device=device)
    f2 = fy * fy + fx * fx
    kernel = propagation_kernel(f2, DZ, NB, LAM)
    exit_kernel = propagation_kernel(f2, -0.5 * n_slices * DZ, NB, LAM) * pupil(f2, NA, LAM, 0.03)
    return v0, dn, target, kernel, exit_kernel


def _package_step(mode):
    phase_per_dn = 2 * math.pi / LAM * DZ

    def step(v0, dn, kernel, exit_kernel, target):
        phi = phase_per_dn * dn
        u = slice_loop(v0, phi, kernel, mode)
        u = torch.fft.ifft2(torch.fft.fft2(u) * exit_kernel)
        intensity = u.real.square() + u.imag.square()
        return (intensity - target).square().mean()
    return step


def bench_size(side, n_slices, batch, device, repeats, modes, graphs=True, naive=True):
    run = _timer(device)
    v0, dn0, target, kernel, exit_kernel = _inputs(side, n_slices, batch, device)
    base = torch.cuda.memory_allocated(device) if device.type == "cuda" else 0
    rows = []
    variants = []
    if naive:
        variants.append(("naive eager autograd", lambda dn: naive_step(v0, dn, kernel, exit_kernel, target, 2 * math.pi / LAM * DZ)))
    for m in modes:
        st = _package_step(m)
        variants.append((f"package {m}", lambda dn, st=st: st(v0, dn, kernel, exit_kernel, target)))
    for name, loss_fn in variants:
        dn = dn0.clone().requires_grad_()

        def fn():
            dn.grad = None
            loss_fn(dn).backward()
        rows.append(_measure(name, fn, device, run, repeats, base))
        dn = None  # frees the volume and its gradient before the next variant
        if device.type == "cuda" and graphs and name.startswith("package"):
            rows.append(_graphed(name, loss_fn, dn0, device, run, repeats))
    return {"image": [side, side], "window": [side, side], "n_slices": n_slices, "batch": batch, "rows": rows}


def _graphed(name, loss_fn, dn0, device, run, repeats):
    """The whole step (forward, backward) captured once in a CUDA graph and replayed."""
    try:
        dn = dn0.clone().requires_grad_()
        s = torch.cuda.Stream()
        s.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(s):
            for _ in range(3):
                dn.grad = None
                loss_fn(dn).backward()
        torch.cuda.current_stream().wait_stream(s)
        graph = torch.cuda.CUDAGraph()
        dn.grad = None
        with torch.cuda.graph(graph):
            loss_fn(dn).backward()
        graph.replay()
        torch.cuda.synchronize(device)
        times = run(graph.replay, repeats)
        out = {"variant": name + " + CUDA graph", "median_s": statistics.median(times), "all_s": times, "peak_gib": None}
        del graph
        return out
    except Exception as exc:  # capture is not possible everywhere; report why
        return {"variant": name + " + CUDA graph", "median_s": None, "error": f"{type(exc).__name__}: {exc}"[:300]}


def bench_model(side, n_slices, batch, device, repeats, modes):
    """The package's full training step on the demo geometry: planned window, sources, gains, calibration off."""
    run = _timer(device)
    o = Optics(wavelength_um=LAM, n_background=NB, na=NA, pixel_size_um=DX, n_slices=n_slices,
               slice_spacing_um=DZ, image_plane_um=0.5 * n_slices * DZ)
    fov = side * DX
    src = source_grid(39, 84.0 * side / 512, 50.0)
    plan = plan_for_sources(o, (side, side), src, warn=False)
    g = torch.Generator().manual_seed(1)
    dn0 = (0.03 * torch.rand((n_slices, side, side), generator=g)).to(device)
    target = torch.rand((batch, side, side), generator=g).to(device)
    s = torch.tensor(src[:batch], dtype=torch.float32, device=device)
    rows = []
    for m in ("autograd", *modes):
        model = MultiSliceModel(o, plan, device=device, backward_mode=m)
        dn = dn0.clone().requires_grad_()

        def fn():
            dn.grad = None
            (model(dn, s) - target).square().mean().backward()
        base = torch.cuda.memory_allocated(device) if device.type == "cuda" else 0
        rows.append(_measure(f"MultiSliceModel {m}", fn, device, run, repeats, base))
    return {"image": [side, side], "window": list(plan.padded_shape), "n_slices": n_slices, "batch": batch,
            "fov_um": fov, "rows": rows}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="auto")
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--quick", action="store_true", help="small sizes (CPU)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    device = resolve_device(args.device)
    modes = ("stored", "reversible", "checkpoint")
    res = {"sizes": [], "model": []}
    if args.quick:
        sizes, mem_sizes, model_sizes = [(128, 14, 8)], [(128, 48, 8)], [(128, 14, 8)]
    else:
        sizes, mem_sizes, model_sizes = [(512, 14, 30), (1024, 24, 30)], [(1024, 96, 30)], [(512, 14, 30)]
    for side, n, b in sizes:
        res["sizes"].append(bench_size(side, n, b, device, args.repeats, modes))
        print(json.dumps(res["sizes"][-1]["rows"], default=str)[:2000], flush=True)
    for side, n, b in mem_sizes:  # the memory target: naive and stored would need ~N fields per image
        res["sizes"].append(bench_size(side, n, b, device, max(3, args.repeats // 4), ("reversible", "checkpoint", "stored"),
                                       graphs=False, naive=True))
    for side, n, b in model_sizes:
        res["model"].append(bench_model(side, n, b, device, args.repeats, modes))
    out = write_document(args.out or results_file("step_speed", device, table=False), res, device)
    print(f"\n{json.loads(out.read_text())['hardware']['name']} ({device}), torch {torch.__version__}")
    print("| grid | window | slices | batch | variant | ms / step | vs naive | peak GiB |")
    print("|---|---|---|---|---|---|---|---|")
    for r in res["sizes"] + res["model"]:
        ref = next((x["median_s"] for x in r["rows"] if x["variant"].startswith("naive") or x["variant"].endswith("autograd")), None)
        for x in r["rows"]:
            t = x.get("median_s")
            ms = f"{1e3 * t:.1f}" if t else x.get("error", "-")
            ratio = f"{ref / t:.2f}×" if (t and ref) else "-"
            pk = f"{x['peak_gib']:.2f}" if x.get("peak_gib") is not None else "-"
            print(f"| {r['image'][0]}² | {r['window'][0]}² | {r['n_slices']} | {r['batch']} | {x['variant']} | {ms} | {ratio} | {pk} |")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
