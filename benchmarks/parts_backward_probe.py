"""Each kept "auto" model part's effect in the final state of a default run (issue 49's backward step, measured alone).

Usage (repository root)::

    python -m benchmarks run scenes make beads_high cells_fine      # out/scenes/NAME
    python -m benchmarks run parts_backward_probe SCENE [--seed S]

Runs the defaults with ``parts_backward`` off (the run the choice alone makes), then
:func:`napari_fdt.recon.choices.parts_backward.marginal_effects` on its final state: per kept part the held-out error with it
taken out, the paired change and its standard error, and whether it earns its place. One JSON row per run is appended
to ``benchmarks/results/parts_backward_cpu.jsonl`` (with the Δn error against the scene's truth and the run's seconds).
"""

from __future__ import annotations

import argparse
import json
import time

from benchmarks._results import append_row, code_version, results_file
from benchmarks.scenes import folder_of


def main(argv: list[str] | None = None) -> None:
    import torch

    from napari_fdt import read_acquisition, read_volume_tiff
    from napari_fdt.recon.assess.metrics import relative_delta_n_error
    from napari_fdt.recon.choices.parts_backward import marginal_effects
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig

    ap = argparse.ArgumentParser(prog="python -m benchmarks run parts_backward_probe")
    ap.add_argument("scene")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    folder = folder_of(args.scene)
    acq = read_acquisition(folder)
    truth = read_volume_tiff(folder / "ground_truth_ri.tif")[0]
    cfg = SolverConfig.from_dict({**SolverConfig().to_dict(), "seed": args.seed, "parts_backward": False})
    t0 = time.perf_counter()
    rec = Reconstructor(acq, cfg, device="cpu")
    for _ in rec.run():
        pass
    seconds = time.perf_counter() - t0
    stage = rec._build_stage(len(rec.config.stages) - 1)
    eff = marginal_effects(rec, stage, rec._loss_mask(stage))
    row = {"scene": args.scene, "seed": args.seed, "code": code_version(), "threads": args.threads,
           "parts": [p for p, on in rec.parts.items() if on],
           "delta_n_error": relative_delta_n_error(rec.delta_n_full(), truth - acq.optics.n_background), "seconds": seconds,
           "reference_error": eff["reference_error"], "probe_s": eff["seconds"],
           "effects": [{k: v for k, v in e.items() if k != "image_errors_without"} for e in eff["effects"]]}
    append_row(results_file("parts_backward", "cpu"), row)
    for e in row["effects"]:
        z = e["improvement"] / e["standard_error"] if e["standard_error"] else float("nan")
        print(f"{args.scene} seed {args.seed}: {e['part']}: held-out error {100 * e['improvement'] / eff['reference_error']:+.2f} % "
              f"without it ({z:.1f} SE): {'earns its place' if e['earns'] else 'dropped'}")
    print(json.dumps({k: row[k] for k in ("parts", "delta_n_error", "seconds")}))


if __name__ == "__main__":
    main()
