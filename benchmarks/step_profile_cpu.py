"""The sample's finest step against the naive step on the CPU, and where the step's time goes (docs/benchmarks.md,
"The finest step against the naive step on the CPU").

    python -m benchmarks run step_profile_cpu [--acquisition DIR] [--pixel-integration] [--field-window full|split]
                                              [--frozen-sources] [--repeats 10] [--profile] [--parts] [--loop 60]
                                              [--naive-window planned|same]

Times ``Reconstructor._step`` on an acquisition's (default the bundled sample's) finest stage (factor 1, TV 1/0.5,
parts off, the default validation split: held-out images in a batch run through the model separately; the sources'
positions and depths trained, as the finest stage of a run trains them, unless ``--frozen-sources``, the setting of
the records before 2026-11-26 night) and ``benchmarks/naive_step.py`` on the
planned full window (the one a plain multi-slice step needs: the split-field model's own window is smaller), batch and
slices, in one process (host clock, after warm-up). ``--profile`` prints torch.profiler's
operator table of 5 steps, by operator and by operator and shape. Nothing is asserted; this reports.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from benchmarks.naive_step import naive_step  # noqa: E402
from napari_fdt.data.io import read_acquisition  # noqa: E402
from napari_fdt.recon.calibration.adam import Adam  # noqa: E402
from napari_fdt.recon.run.solver import Reconstructor  # noqa: E402
from napari_fdt.recon.settings.config import SolverConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def finest_stage_config(iterations: int = 1000, **settings) -> SolverConfig:
    """The settings of the finest stage run alone: factor 1 for ``iterations``, TV 1/0.5, parts off, no early stopping,
    ``settings`` on top."""
    return SolverConfig.from_dict({**SolverConfig().to_dict(), "tv_xy_weight": 1.0, "tv_z_weight": 0.5,
                                   "stages": [{"factor": 1, "iterations": iterations, "batch_size": None}],
                                   "final_stage_min_passes": 0, "early_stopping": "off", "calibrate_pupil": False,
                                   "calibrate_aberrations": False, "obliquity_correction": False, "coherence": "mask",
                                   **settings})


def finest_stage_step(acquisition, device: str = "cpu", **settings):
    """``Reconstructor._step`` of ``acquisition``'s finest stage run alone (factor 1, TV 1/0.5, parts off, no early
    stopping, the default validation split: held-out images in a batch run through the model separately), with
    ``settings`` on top, on ``device``; returns (the step, the Reconstructor, the stage). Shared with
    ``benchmarks/host_syncs.py`` and ``benchmarks/iteration_overhead.py``."""
    cfg = finest_stage_config(**settings)
    rec = Reconstructor(acquisition, cfg, device=device)
    stage = rec._build_stage(0)
    rec._carry_volume_to(stage)
    mask = rec._loss_mask(stage)
    rec._init_gains(stage, mask)
    rec.calibration.set_trainable(0)
    opt = Adam([rec.volume.x], lr=cfg.lr_ri, betas=(0.9, 0.99))  # the stage loop's (recon/loop/stage_loop.new_optimiser)

    def step() -> None:
        rec._step(stage, mask, opt, cfg.batch_size, 1.0, 0.5)

    step.optimiser = opt  # (the RI grid's, for --parts)
    return step, rec, stage


def print_loop(acq, config: SolverConfig, iterations: int) -> None:
    """The same finest stage run by the solver's loop (``Reconstructor.run``, sub-slices and the 2x grid off so that no
    part's test reruns it): its steps' seconds against the stage's wall time; the rest is the loop's (the validation
    error at each snapshot, early stopping's best iterate, the snapshots, set-up)."""
    cfg = SolverConfig.from_dict({**config.to_dict(), "stages": [{"factor": 1, "iterations": iterations, "batch_size": None}],
                                  "early_stopping": "best", "sub_slices": 1, "field_oversampling": 1})
    rec = Reconstructor(acq, cfg, device="cpu")
    spent: list[float] = []
    inner = rec._step

    def timed(*a, **k):
        t0 = time.perf_counter()
        try:
            return inner(*a, **k)
        finally:
            spent.append(time.perf_counter() - t0)

    rec._step = timed
    t0 = time.perf_counter()
    snaps = list(rec.run())
    wall = time.perf_counter() - t0
    print(f"the solver's loop, {len(spent)} iterations, {len(snaps)} snapshots: {1e3 * wall / len(spent):.1f} ms per iteration, "
          f"of which the step {1e3 * sum(spent) / len(spent):.1f} ms; outside the steps {wall - sum(spent):.2f} s "
          f"({100 * (wall - sum(spent)) / wall:.0f} % of the stage's {wall:.2f} s)")


def print_parts(step, rec, repeats: int) -> None:
    """The step's time by part, each part's calls timed with the host clock (the CPU runs them in order): the model's
    images (train and held-out passes), the loss terms (data and TV), the backward pass (the model's adjoint, TV's and
    the loss's gradients), the RI grid's Adam, the calibration's optimisers, and the rest (batch draw, index copies,
    Δn from the grid, the split of held-out images). Prints a table of ms and % per step."""
    import napari_fdt.recon.run.solver as solver

    spent: dict[str, float] = {}

    def timed(name, fn):
        def run(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[name] = spent.get(name, 0.0) + time.perf_counter() - t0
        return run

    patches = [(solver, "spectral_images", "model's images (forward)"), (solver, "total_loss", "loss terms (data, TV)"),
               (torch.Tensor, "backward", "backward (model adjoint, TV, loss)"),
               (step.optimiser, "step", "RI grid's Adam"), (rec.calibration.optimiser, "step", "calibration's optimisers")]
    saved = [(obj, name, getattr(obj, name)) for obj, name, _ in patches]
    for obj, name, label in patches:
        setattr(obj, name, timed(label, getattr(obj, name)))
    try:
        for _ in range(3):
            step()
        spent.clear()
        t0 = time.perf_counter()
        for _ in range(repeats):
            step()
        total = time.perf_counter() - t0
    finally:
        for obj, name, fn in saved:
            setattr(obj, name, fn)
    rows = list(spent.items()) + [("rest (batch, indices, delta_n, split)", total - sum(spent.values()))]
    print("| part | ms per step | % |\n|---|---|---|")
    for name, s in rows:
        print(f"| {name} | {1e3 * s / repeats:.1f} | {100 * s / total:.0f} |")
    print(f"| whole step | {1e3 * total / repeats:.1f} | 100 |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--loop", type=int, default=0, help="also run the same stage through the solver's loop for LOOP iterations "
                    "and report the share of its wall time outside the steps (validation, snapshots, bookkeeping)")
    ap.add_argument("--parts", action="store_true", help="the step's milliseconds by part (forward, loss, backward, optimisers, rest)")
    ap.add_argument("--acquisition", default=str(ROOT / "sample_data" / "letters"), help="default: the bundled sample")
    ap.add_argument("--pixel-integration", action="store_true", help="the camera's pixel integration on")
    ap.add_argument("--field-window", default="auto", choices=["auto", "full", "split"], help="the solver setting (auto: split on CPU)")
    ap.add_argument("--frozen-sources", action="store_true", help="the sources' positions not trained (before 2026-11-26 night)")
    ap.add_argument("--naive-window", default="planned", choices=["planned", "same"],
                    help="the naive step's window: the planned full window (what a plain multi-slice step needs) or the "
                         "package's own (issue 48's comparison: the same window, batch and slices)")
    args = ap.parse_args()
    acq = read_acquisition(args.acquisition)
    step, rec, stage = finest_stage_step(acq, pixel_integration=args.pixel_integration, field_window=args.field_window,
                                         calibration_from_stage=1 if args.frozen_sources else 0)
    cfg = rec.config

    from napari_fdt.recon.problem.stages import multislice_plan

    h, w = multislice_plan(acq.optics, 1, acq.image_shape, rec.calibration.sources_um())[3].padded_shape
    if args.naive_window == "same":
        h, w = stage.window
    b, n = cfg.batch_size, acq.optics.n_slices
    v0 = torch.randn(b, h, w, dtype=torch.complex64)
    dn = torch.zeros(n, h, w, requires_grad=True)
    kernel = torch.exp(1j * torch.rand(h, w)).to(torch.complex64)
    target = torch.rand(b, h, w)

    def naive() -> None:
        naive_step(v0, dn, kernel, kernel, target, 10.0).backward()

    times = {}
    for name, fn in (("package", step), ("naive", naive)):
        for _ in range(3):
            fn()
        t0 = time.perf_counter()
        for _ in range(args.repeats):
            fn()
        times[name] = (time.perf_counter() - t0) / args.repeats
    which = "the package's" if args.naive_window == "same" else "the planned full window"
    print(f"package's window {stage.window[0]}x{stage.window[1]}, naive's ({which}) {h}x{w}, {n} slices, "
          f"batch {b}, {torch.get_num_threads()} threads: package {1e3 * times['package']:.1f} ms, "
          f"naive {1e3 * times['naive']:.1f} ms, package {times['naive'] / times['package']:.2f}x faster")
    if args.parts:
        print_parts(step, rec, args.repeats)
    if args.loop:
        print_loop(acq, rec.config, args.loop)
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            for _ in range(5):
                step()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
        print(prof.key_averages(group_by_input_shape=True).table(sort_by="self_cpu_time_total", row_limit=20))


if __name__ == "__main__":
    main()
