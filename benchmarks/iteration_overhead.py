"""The solver's finest iteration against its model's step, in one process (issue 48: "the demo's finest iteration
≤ 1.15× its model step").

    python -m benchmarks run iteration_overhead [--device cuda] [--scene demo|sample] [--iterations 40] [--rounds 3]

Builds the scene (``demo``: the demo geometry of ``benchmarks/suite.py``, 512² px, 14 slices, 169 sources on a 13×13
grid, simulated on ``--device``; ``sample``: the bundled sample), then times, in alternating rounds:

- **model step**: the finest stage's model alone on one batch (the stage's batch size, the same rows every time):
  images, an L2 loss against the measured images, the backward pass to Δn; no optimiser, no calibration;
- **product step**: ``Reconstructor._step`` of the same stage (``benchmarks/step_profile_cpu.finest_stage_step``:
  TV 1/0.5, the sources and gains trained, parts off, the held-out images of a batch in their own pass, both Adams);
- **solver iteration**: the same stage run by ``Reconstructor.run`` (``calibration_from_stage`` 0), timed over
  ``--iterations`` iterations after 20 (the loop's snapshots and checks included).

Each time is the wall time of that many calls between two device synchronisations, divided by the count (the host
may run ahead of the device within it, as in a run). Prints one JSON row per round and the medians, and appends the
medians to ``benchmarks/results/iteration_overhead_DEVICE.jsonl``. Nothing is asserted; this reports.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from benchmarks._results import append_row, results_file
from benchmarks.step_profile_cpu import ROOT, finest_stage_config, finest_stage_step
from napari_fdt.data.io import read_acquisition
from napari_fdt.recon.run.solver import Reconstructor


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _per_call_ms(fn, calls: int, device: torch.device) -> float:
    """Milliseconds per call of ``fn`` over ``calls`` calls between two synchronisations."""
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(calls):
        fn()
    _sync(device)
    return 1e3 * (time.perf_counter() - t0) / calls


def model_step(rec, stage, batch: int):
    """The stage model's images, L2 loss and backward to Δn for ``batch`` fixed images (no optimiser)."""
    idx = torch.arange(batch, device=stage.images.device)
    src = stage.stage_sources(rec.calibration.calibrated_sources().detach()[idx])
    target = stage.images[idx]
    dn = rec.volume.delta_n().detach().clone().requires_grad_(True)

    def step() -> None:
        dn.grad = None
        pred = stage.model(stage.to_field_grid(dn), src)
        loss = ((pred - target) ** 2).mean()
        loss.backward()
    return step


def solver_iteration_ms(acq, settings: dict, device: str, iterations: int, skip: int = 20) -> float:
    """Milliseconds per iteration of the finest stage run by ``Reconstructor.run``, iterations skip … skip+iterations."""
    rec = Reconstructor(acq, finest_stage_config(100000, **{"calibration_from_stage": 0, **settings}), device=device)
    dev = torch.device(device)
    marks: list[float] = []
    count = [0]

    def tick() -> bool:
        count[0] += 1
        if count[0] in (skip, skip + iterations):
            _sync(dev)
            marks.append(time.perf_counter())
        return count[0] >= skip + iterations
    for _ in rec.run(should_stop=tick):
        pass
    if len(marks) < 2:
        raise RuntimeError(f"the run stopped after {count[0]} iterations, before {skip + iterations}")
    return 1e3 * (marks[1] - marks[0]) / iterations


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--scene", default="demo", choices=["demo", "sample"])
    ap.add_argument("--iterations", type=int, default=40, help="calls per timing")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--batch", type=int, default=30, help="images per batch (the demo's 30; the sample's default 16)")
    args = ap.parse_args()
    dev = torch.device(args.device)
    if args.scene == "demo":
        from benchmarks.suite import _letters_scene
        acq, _ = _letters_scene(512, 14, 13, 84.0, 100, dev, text="UCDAVIS")
    else:
        acq = read_acquisition(ROOT / "sample_data" / "letters")
    settings = {"batch_size": args.batch, "calibration_from_stage": 0}
    step, rec, stage = finest_stage_step(acq, device=args.device, **settings)
    model = model_step(rec, stage, args.batch)
    for _ in range(5):  # warm-up: plans, kernels, allocator
        step()
        model()
    rows = []
    for r in range(args.rounds):
        row = {"round": r, "model_step_ms": _per_call_ms(model, args.iterations, dev),
               "product_step_ms": _per_call_ms(step, args.iterations, dev),
               "solver_iteration_ms": solver_iteration_ms(acq, settings, args.device, args.iterations)}
        print(json.dumps({k: round(v, 2) for k, v in row.items()}), flush=True)
        rows.append(row)
    med = {k: statistics.median(r[k] for r in rows) for k in ("model_step_ms", "product_step_ms", "solver_iteration_ms")}
    out = {"scene": args.scene, "batch": args.batch, "iterations": args.iterations, "rounds": args.rounds, **med,
           "solver_over_model": med["solver_iteration_ms"] / med["model_step_ms"],
           "product_over_model": med["product_step_ms"] / med["model_step_ms"]}
    print(json.dumps(out))
    append_row(results_file("iteration_overhead", args.device), out, args.device)


if __name__ == "__main__":
    main()
