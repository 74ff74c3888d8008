"""Where the time of one training step goes on a GPU: primitive costs and a kernel-level profile.

    python -m benchmarks run profile_step [--side 1024 --slices 24 --batch 30] [--solver-demo | --solver-only]
    python -m benchmarks run profile_step --solver-only --device cpu --solver-side 96   # a quick check on the CPU

Prints (1) the two ceilings: a device-to-device copy of one batch of fields (bytes read + written) and
one batched fft2 of it; (2) each elementwise primitive of the slice loop; (3) the top CUDA kernels of
one full step in each backward mode (torch.profiler). ``--solver-demo`` also profiles one iteration of
each stage of the solver on the demo geometry. Notes and predictions: ``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import statistics

import torch

from benchmarks.step_speed import _inputs, _package_step, _timer  # noqa: E402


def bench(fn, repeats=30):
    """Median milliseconds of ``fn`` on the GPU after 3 warm-up calls (CUDA events)."""
    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    return 1e3 * statistics.median(_timer(torch.device("cuda"))(fn, repeats))


def primitives(side, n, batch):
    from napari_fdt.model import _triton_slice
    v0, dn, target, kernel, exit_kernel = _inputs(side, n, batch, torch.device("cuda"))
    u = v0.clone()
    gbytes = u.numel() * 8 / 1e9
    rows = [("clone (copy)", bench(lambda: u.clone()), 2 * gbytes)]
    rows.append(("fft2", bench(lambda: torch.fft.fft2(u)), 2 * gbytes))
    rows.append(("ifft2", bench(lambda: torch.fft.ifft2(u)), 2 * gbytes))
    rows.append(("fft2(dim=-1) only", bench(lambda: torch.fft.fft(u, dim=-1)), 2 * gbytes))
    rows.append(("u.mul_(K) broadcast", bench(lambda: u.mul_(kernel)), 2 * gbytes))
    phi = dn[0] * 10
    rows.append(("polar(1, phi) (one screen)", bench(lambda: torch.polar(torch.ones_like(phi), phi)), phi.numel() * 12 / 1e9))
    g = v0.clone()
    if _triton_slice.available():
        rows.append(("triton adjoint (g, u → g, Σ)", bench(lambda: _triton_slice.adjoint_screen(g, u, phi, None)), 3 * gbytes))
        pair = torch.stack([u, g])
        rows.append(("triton adjoint + v (reversible)", bench(lambda: _triton_slice.adjoint_screen(pair[1], pair[0], phi, pair[0])), 4 * gbytes))
    rows.append(("torch adjoint Σ Im(g conj u)", bench(lambda: (g.imag * u.real - g.real * u.imag).sum(0)), 2 * gbytes))
    print(f"\nprimitives on ({batch}, {side}, {side}) complex64 = {gbytes:.3f} GB per batch of fields")
    print("| op | ms | GB moved (ideal) | GB/s |")
    print("|---|---|---|---|")
    for name, ms, gb in rows:
        print(f"| {name} | {ms:.3f} | {gb:.3f} | {gb / (ms / 1e3):.0f} |")


def profile_modes(side, n, batch):
    from torch.profiler import ProfilerActivity, profile
    v0, dn0, target, kernel, exit_kernel = _inputs(side, n, batch, torch.device("cuda"))
    for mode in ("stored", "reversible"):
        st = _package_step(mode)
        dn = dn0.clone().requires_grad_()

        def fn():
            dn.grad = None
            st(v0, dn, kernel, exit_kernel, target).backward()
        ms = bench(fn, 10)
        with profile(activities=[ProfilerActivity.CUDA, ProfilerActivity.CPU]) as prof:
            fn()
            torch.cuda.synchronize()
        print(f"\n=== step {mode}: {ms:.1f} ms ({side}², {n} slices, batch {batch}) ===")
        print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=14, max_name_column_width=60))


def profile_solver_demo(device: str = "cuda", side: int = 512, n_slices: int = 14, n_grid: int = 13, overrides: dict | None = None) -> None:
    """Ten steady iterations of a one-stage solver run per coarse-to-fine factor on the demo geometry (fewer images),
    under ``torch.profiler``: the solver's iteration against the model's step (``step_speed``), what runs between.

    The profiler steps from the solver's per-iteration ``should_stop`` call, on a schedule (15 iterations skipped,
    5 warm-up, 10 recorded), so the set-up (plans, cuFFT plans, Triton compilation) stays out of the tables: profiling
    a whole 40-iteration stage, set-up included, left tables that took over 80 s to build (2026-11-26, H100, cut by the
    item's limit). Fixed TV weights: the TV choice's trials would change the iteration count."""
    import time

    from torch.profiler import ProfilerActivity, profile, schedule

    from benchmarks.suite import _letters_scene
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig, StageConfig

    dev = torch.device(device)
    acq, dn = _letters_scene(side, n_slices, n_grid, 84.0 * side / 512, side // 5, dev, text="UCDAVIS")
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    sort_device = "cuda_time_total" if dev.type == "cuda" else "cpu_time_total"
    for factor in (4, 2, 1):
        # calibration_from_stage 0: the sources train in this one stage, as in a real run's later stages (with the
        # default 1 a one-stage run never calibrates them, and {"calibrate_sources": false} changed nothing, H100
        # 2026-11-26)
        cfg = SolverConfig(stages=[StageConfig(factor, 40)], batch_size=30, snapshot_every=1000,
                           tv_xy_weight=1.0, tv_z_weight=0.5, calibration_from_stage=0)
        if overrides:  # e.g. {"calibrate_sources": false}: what a part of the iteration costs
            cfg = SolverConfig.from_dict({**cfg.to_dict(), **overrides})
        rec = Reconstructor(acq, cfg, device=device)
        ticks: list[float] = []
        with profile(activities=activities, schedule=schedule(wait=15, warmup=5, active=10, repeat=1)) as prof:
            def tick() -> bool:
                if dev.type == "cuda":
                    torch.cuda.synchronize()
                ticks.append(time.perf_counter())
                prof.step()
                return False
            for _ in rec.run(should_stop=tick):
                pass
        steady = [b - a for a, b in zip(ticks[20:30], ticks[21:31])]
        print(f"\n=== solver, one stage at factor {factor} ({side}², {n_slices} slices, batch 30, {device}): "
              f"{1e3 * statistics.median(steady):.1f} ms per iteration (median of iterations 21-30, synchronised); "
              f"the stage record {rec.stages[0].seconds_per_iteration * 1e3:.1f} ms/it ===", flush=True)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=15, max_name_column_width=50))
        print(prof.key_averages().table(sort_by=sort_device, row_limit=12, max_name_column_width=50), flush=True)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--side", type=int, default=1024)
    p.add_argument("--slices", type=int, default=24)
    p.add_argument("--batch", type=int, default=30)
    p.add_argument("--solver-demo", action="store_true")
    p.add_argument("--no-modes", action="store_true")
    p.add_argument("--solver-only", action="store_true", help="only the solver's profile (--solver-demo)")
    p.add_argument("--device", default="cuda", help="the solver profile's device (cpu: a quick check of the script)")
    p.add_argument("--solver-side", type=int, default=512, help="the solver profile's grid side, px")
    p.add_argument("--solver-set", default=None, help="JSON settings for the solver profile, e.g. '{\"calibrate_sources\": false}'")
    a = p.parse_args()
    if not a.solver_only:
        primitives(a.side, a.slices, a.batch)
        if not a.no_modes:
            profile_modes(a.side, a.slices, a.batch)
    if a.solver_demo or a.solver_only:
        import json
        profile_solver_demo(a.device, a.solver_side, overrides=json.loads(a.solver_set) if a.solver_set else None)


if __name__ == "__main__":
    main()
