"""The sample's finest step against the naive step on the CPU, and where the step's time goes (docs/benchmarks.md,
"The finest step against the naive step on the CPU").

    python -m benchmarks run step_profile_cpu [--acquisition DIR] [--pixel-integration] [--field-window full|split]
                                              [--frozen-sources] [--repeats 10] [--profile]

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
from napari_fdt.recon.run.solver import Reconstructor  # noqa: E402
from napari_fdt.recon.settings.config import SolverConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def finest_stage_step(acquisition, **settings):
    """``Reconstructor._step`` of ``acquisition``'s finest stage run alone (factor 1, TV 1/0.5, parts off, no early
    stopping, the default validation split: held-out images in a batch run through the model separately), with
    ``settings`` on top; returns (the step, the Reconstructor, the stage). Shared with ``benchmarks/host_syncs.py``."""
    cfg = SolverConfig.from_dict({**SolverConfig().to_dict(), "tv_xy_weight": 1.0, "tv_z_weight": 0.5,
                                  "stages": [{"factor": 1, "iterations": 1000, "batch_size": None}], "final_stage_min_passes": 0,
                                  "early_stopping": "off", "calibrate_pupil": False, "calibrate_aberrations": False,
                                  "obliquity_correction": False, "coherence": "mask", **settings})
    rec = Reconstructor(acquisition, cfg, device="cpu")
    stage = rec._build_stage(0)
    rec._carry_volume_to(stage)
    mask = rec._loss_mask(stage)
    rec._init_gains(stage, mask)
    rec.calibration.set_trainable(0)
    opt = torch.optim.Adam([rec.volume.x], lr=cfg.lr_ri)

    def step() -> None:
        rec._step(stage, mask, opt, cfg.batch_size, 1.0, 0.5)

    return step, rec, stage


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--acquisition", default=str(ROOT / "sample_data" / "letters"), help="default: the bundled sample")
    ap.add_argument("--pixel-integration", action="store_true", help="the camera's pixel integration on")
    ap.add_argument("--field-window", default="auto", choices=["auto", "full", "split"], help="the solver setting (auto: split on CPU)")
    ap.add_argument("--frozen-sources", action="store_true", help="the sources' positions not trained (before 2026-11-26 night)")
    args = ap.parse_args()
    acq = read_acquisition(args.acquisition)
    step, rec, stage = finest_stage_step(acq, pixel_integration=args.pixel_integration, field_window=args.field_window,
                                         calibration_from_stage=1 if args.frozen_sources else 0)
    cfg = rec.config

    from napari_fdt.recon.problem.stages import multislice_plan

    h, w = multislice_plan(acq.optics, 1, acq.image_shape, rec.calibration.sources_um())[3].padded_shape
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
    print(f"package's window {stage.window[0]}x{stage.window[1]}, naive's (the planned full window) {h}x{w}, {n} slices, "
          f"batch {b}, {torch.get_num_threads()} threads: package {1e3 * times['package']:.1f} ms, "
          f"naive {1e3 * times['naive']:.1f} ms, package {times['naive'] / times['package']:.2f}x faster")
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            for _ in range(5):
                step()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
        print(prof.key_averages(group_by_input_shape=True).table(sort_by="self_cpu_time_total", row_limit=20))


if __name__ == "__main__":
    main()
