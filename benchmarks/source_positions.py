"""Source positions against the truth: fits with the volume held fixed, per stage model (issue 12, item 4).

Usage (repository root)::

    python -m benchmarks run source_positions fixed --scene out/scenes/letters128 --factor 2 --model envelope
    python -m benchmarks run source_positions fixed --scene out/scenes/letters128 --factor 1 --model multislice --start truth
    python -m benchmarks run source_positions run --scene letters128 --setting 0 --set '{"multislice_source_step_scale": 1}'

``fixed`` builds one solver stage (``factor``, ``model``), sets the RI to the scene's ground truth (block-averaged
to the stage grid) or to zero (``--volume zero``), and trains only the calibration (positions, per-source depths,
the common depth offset, gains) with the solver's own loss, batches and optimiser for ``--iterations``. It prints
the calibrated positions' error against ``ground_truth_sources_um.json`` along the way: the lateral RMS (µm), its
common mean shift, the per-source depth RMS about the mean and the mean depth error (µm). With the volume at the
truth, what remains is the model's bias (where the fit converges) and the step's speed (how fast it gets there).
``--start``: ``initial`` (the acquisition's positions), ``truth``, or ``truth_depth`` (true depths, initial x, y).

``run`` is a full default reconstruction of a scene of ``benchmarks/regularisation.py``'s suite (TV ``--setting``, other
settings ``--set``), the source errors traced every 40 iterations of each stage; the row, with its ``trace``, goes to
``results/source_positions_runs_cpu.jsonl``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks._results import append_row, results_file


def errors(sources_um: np.ndarray, truth_um: np.ndarray) -> dict[str, float]:
    """Lateral RMS, its mean shift, depth RMS about the mean depth error, and the mean depth error (µm)."""
    e = np.asarray(sources_um, dtype=np.float64) - np.asarray(truth_um, dtype=np.float64)
    return {"lateral_rms_um": float(np.sqrt((e[:, :2] ** 2).sum(1).mean())),
            "lateral_mean_um": float(np.hypot(*e[:, :2].mean(0))),
            "depth_rms_um": float(e[:, 2].std()), "depth_mean_um": float(e[:, 2].mean())}


def _line(r: dict) -> str:
    return (f"it {r['iteration']:4d}  lateral {r['lateral_rms_um']:.3f} (mean {r['lateral_mean_um']:.3f})  depth {r['depth_rms_um']:.3f} "
            f"(mean {r['depth_mean_um']:+.3f}, offset {r['depth_offset_um']:+.3f})  {r.get('seconds', 0):.0f} s")


def fixed_volume_fit(folder: Path, factor: int, model: str, start: str = "initial", iterations: int = 200,
                     batch_size: int = 16, volume: str = "truth", every: int = 20, seed: int = 0,
                     overrides: dict | None = None, verbose: bool = False, freeze_depth: bool = False) -> list[dict]:
    """Train the calibration only, the volume fixed; returns the error rows (one per ``every`` iterations)."""
    from napari_fdt import read_acquisition, read_volume_tiff
    from napari_fdt.recon.problem.losses import total_loss
    from napari_fdt.recon.problem.stages import block_average
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig

    acq = read_acquisition(folder)
    truth_ri, _ = read_volume_tiff(folder / "ground_truth_ri.tif")
    truth_src = np.array(json.loads((folder / "ground_truth_sources_um.json").read_text())["sources_um"])
    init = np.array(acq.sources_um, dtype=np.float64)
    if start == "truth":
        init = truth_src.copy()
    elif start == "truth_depth":
        init[:, 2] = truth_src[:, 2]
    cfg = SolverConfig.from_dict({**SolverConfig().to_dict(), "stages": [{"factor": factor, "iterations": iterations}],
                                  "coarse_model": model, "validation_fraction": 0.0, "tv_xy_weight": 0.0, "tv_z_weight": 0.0,
                                  "calibration_from_stage": 0, "batch_size": batch_size, "seed": seed, **(overrides or {})})
    rec = Reconstructor(acq, cfg, device="cpu", initial_sources_um=init)
    stage = rec._build_stage(0)
    if model == "envelope" and factor == 1:  # the envelope model on the acquisition's grid (the solver uses it at factor > 1 only)
        from napari_fdt.model.envelope import EnvelopeModel
        from napari_fdt.recon.problem.stages import Stage

        h, w = acq.image_shape
        env = EnvelopeModel(acq.optics, (h, w), 1, (0.0, 0.0))
        stage = Stage(0, 1, 1, iterations, acq.optics, env, rec.images, (0.0, 0.0), (h, w), env.padded)
        stage.coverage = env.coverage(torch.as_tensor(init, dtype=torch.float32))
    dn = torch.as_tensor(truth_ri - acq.optics.n_background, dtype=torch.float32)
    dn = block_average(dn, factor)[:, : stage.grid_shape[0], : stage.grid_shape[1]] if volume == "truth" else \
        torch.zeros((acq.optics.n_slices, *stage.grid_shape))
    mask = rec._loss_mask(stage)
    rec._init_gains(stage, mask)
    cal = rec.calibration
    cal.set_trainable(0)
    if freeze_depth:  # each source's own depth stays at its start (the common offset follows calibrate_source_depth)
        cal.sources.register_hook(lambda g: g * torch.tensor([1.0, 1.0, 0.0], dtype=g.dtype))
    opt = cal.optimiser
    data_range = float(stage.images.max())
    rows = [{"iteration": 0, **errors(cal.sources_um(), truth_src), "depth_offset_um": 0.0}]
    t0 = time.perf_counter()
    for it in range(1, iterations + 1):
        idx = rec.batches.next(batch_size)
        pred = rec._predict_normalised(stage, dn, idx)
        loss, _ = total_loss(pred, stage.images[idx], dn, rec.loss_weights, it / iterations,
                             mask=None if mask is None else mask[idx], data_range=data_range)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if it % every == 0 or it == iterations:
            rows.append({"iteration": it, **errors(cal.sources_um(), truth_src),
                         "depth_offset_um": float(cal.depth_offset_um.detach()), "seconds": time.perf_counter() - t0})
            if verbose:
                print(_line(rows[-1]), flush=True)
    return rows


def traced_run(scene: str, setting: str, overrides: dict | None = None, every: int = 40, verbose: bool = False) -> dict:
    """One full default reconstruction of a suite scene (``benchmarks/regularisation.py``'s ``run_one`` row) with the
    source errors traced every ``every`` iterations of each stage and at each stage's end (``trace``)."""

    from benchmarks import regularisation as suite

    trace: list[dict] = []

    def record(rec, snap, truth_src, t0) -> None:
        if snap.iteration % every == 0 or snap.stage_complete:
            trace.append({"stage": snap.stage, "iteration": snap.iteration, **errors(rec.sources_um(), truth_src),
                          "depth_offset_um": float(rec.calibration.depth_offset_um.detach()), "seconds": time.perf_counter() - t0})
            if verbose:
                print(f"stage {snap.stage} " + _line(trace[-1]), flush=True)

    return {**suite.run_one(scene, setting, "cpu", overrides, on_snapshot=record), "trace": trace}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("fixed")
    f.add_argument("--scene", type=Path, required=True)
    f.add_argument("--factor", type=int, default=1)
    f.add_argument("--model", default="multislice", choices=["envelope", "multislice"])
    f.add_argument("--start", default="initial", choices=["initial", "truth", "truth_depth"])
    f.add_argument("--volume", default="truth", choices=["truth", "zero"])
    f.add_argument("--iterations", type=int, default=200)
    f.add_argument("--batch-size", type=int, default=16)
    f.add_argument("--every", type=int, default=20)
    f.add_argument("--set", default="{}", help="JSON object of other settings (e.g. '{\"source_step\": \"per_visit\"}')")
    f.add_argument("--freeze-depth", action="store_true", help="keep each source's own depth at its start")
    f.add_argument("--out", type=Path, help="append the rows, one JSON object per line, to this file")
    r = sub.add_parser("run", help="a full reconstruction of a suite scene, the source errors traced along the way")
    r.add_argument("--scene", required=True, help="a scene of benchmarks/regularisation.py (sample, letters128, beads, cells, deep)")
    r.add_argument("--setting", default="auto", help='TV setting as in regularisation.py: "auto" or a weight τ_xy')
    r.add_argument("--set", default="{}", help="JSON object of other settings")
    r.add_argument("--out", type=Path, default=results_file("source_positions_runs", "cpu"))
    args = p.parse_args(argv)
    overrides = json.loads(args.set)
    if args.cmd == "run":
        row = traced_run(args.scene, args.setting, overrides, verbose=True)
        append_row(args.out, row)
        print(f"{args.scene} {args.setting} {overrides}: Δn error {row['relative_delta_n_error']:.3f}, sources lateral "
              f"{row['source_lateral_rms_um']:.3f} µm, depth {row['source_depth_rms_um']:.3f} µm, {row['wall_s']:.0f} s", flush=True)
        return
    rows = fixed_volume_fit(args.scene, args.factor, args.model, args.start, args.iterations, args.batch_size,
                            args.volume, args.every, overrides=overrides, verbose=True,
                            freeze_depth=args.freeze_depth)
    if args.out:
        append_row(args.out, {"scene": str(args.scene), "factor": args.factor, "model": args.model, "start": args.start,
                              "volume": args.volume, "batch_size": args.batch_size, "set": overrides, "rows": rows})


if __name__ == "__main__":
    main()
