"""Cold time to the authors' demo accuracy: normalised PSNR ≥ 24 and SSIM ≥ 0.59 (issue 16, item 3; GPU).

    python -m benchmarks run time_to_accuracy --device cuda                          # demo geometry, the suite's demo settings
    python -m benchmarks run time_to_accuracy --device cuda --coarse-model envelope  # same, envelope coarse stages

Run it as the first thing in a fresh process on a freshly started machine: that is the *cold* time. The demo scene
(``benchmarks/suite.py``'s ``demo``: 512²×14, 1521 sources, letters Δn 0.03) is simulated first, not timed. Two
clocks: ``solver_s`` from the ``Reconstructor``'s construction (data in memory, as ``docs/benchmarks.md``'s 14.6 s),
and ``process_s`` from the start of this process (imports, CUDA initialisation and the simulation included). The
suite's metric evaluations (``napari_fdt.recon.assess.metrics.paper_normalised_metrics`` every ``--eval-every`` iterations)
are excluded from ``solver_s``; the first evaluation meeting both targets ends the run, so the time is an upper bound
by at most ``--eval-every`` iterations. Speed-up = 720 s (the authors' ≈ 12 minutes for 500 iterations on one H100)
over ``solver_s``; the issue asks for ≥ 100×. Appends a JSON line to ``benchmarks/results/time_to_accuracy_<device>.jsonl``.
"""

from __future__ import annotations

import time

PROCESS_START = time.perf_counter()

import argparse  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from benchmarks._results import append_row, results_file  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

AUTHORS_S = 720.0


def main() -> None:
    from benchmarks.suite import demo_config, scene_demo, scene_sample
    from napari_fdt import resolve_device
    from napari_fdt.recon.assess.metrics import paper_normalised_metrics
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda")
    p.add_argument("--scene", default="demo", choices=("demo", "sample"), help="sample: the bundled one, a quick check on CPU")
    p.add_argument("--coarse-model", default=None, help="override coarse_model (default: the configuration's, auto)")
    p.add_argument("--iterations", default="150,150,700", help="iterations of the ×4, ×2, ×1 stages")
    p.add_argument("--eval-every", type=int, default=10)
    p.add_argument("--psnr", type=float, default=24.0)
    p.add_argument("--ssim", type=float, default=0.59)
    args = p.parse_args()
    device = resolve_device(args.device)
    its = tuple(int(v) for v in args.iterations.split(","))
    if args.scene == "demo":
        acq, truth, cfg = scene_demo(device, its, demo_config(its))
    else:
        acq, truth, cfg = scene_sample(device)
    if args.coarse_model:
        cfg = SolverConfig.from_dict(dict(cfg.to_dict(), coarse_model=args.coarse_model))
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    solver_s = 0.0
    t0 = time.perf_counter()
    rec = Reconstructor(acq, cfg, device=device)
    gen = rec.run()
    solver_s += time.perf_counter() - t0
    reached = None
    last = -10**9
    history = []
    while True:
        t1 = time.perf_counter()
        try:
            snap = next(gen)
        except StopIteration:
            solver_s += time.perf_counter() - t1
            break
        solver_s += time.perf_counter() - t1
        if snap.phase == "tv_choice":  # the TV choice (its time counts; its volumes are not the run's)
            continue
        if snap.global_iteration - last >= args.eval_every or snap.stage_complete:
            last = snap.global_iteration
            m = paper_normalised_metrics(snap.delta_n_full(), truth)
            history.append({"solver_s": solver_s, "iteration": snap.global_iteration, "stage": snap.stage,
                            "psnr": m["psnr"], "ssim": m["ssim"]})
            print(f"{solver_s:7.2f} s  it {snap.global_iteration:5d}  stage {snap.stage}  PSNR {m['psnr']:.2f}  SSIM {m['ssim']:.3f}", flush=True)
            if m["psnr"] >= args.psnr and m["ssim"] >= args.ssim:
                reached = {"solver_s": solver_s, "process_s": time.perf_counter() - PROCESS_START, **history[-1]}
                break
    row = {"scene": args.scene, "device": str(device), "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
           "torch": torch.__version__, "coarse_model": cfg.coarse_model, "iterations": list(its), "eval_every": args.eval_every,
           "targets": {"psnr": args.psnr, "ssim": args.ssim}, "reached": reached,
           "speed_up_vs_720s": AUTHORS_S / reached["solver_s"] if reached else None, "history": history}
    append_row(results_file("time_to_accuracy", device), row, device)
    if reached:
        print(f"targets reached at {reached['solver_s']:.2f} s of solver time ({reached['process_s']:.1f} s since the process "
              f"started): {AUTHORS_S / reached['solver_s']:.0f}× sooner than 720 s")
    else:
        print("targets not reached")


if __name__ == "__main__":
    main()
