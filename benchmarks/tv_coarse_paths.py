"""Issue 25 experiment: does the finest stage's first look at each weight's coarse volume rank the weights?

    python -m benchmarks run tv_coarse_paths SCENE --seed S [--taus 1,3,10,30] [--probe 40]
    # → benchmarks/results/tv_coarse_paths_cpu.jsonl

For each weight τ (τ_xy = τ, τ_z = τ/2 in every stage) the run's stages before the finest run as the fixed-weight run
of ``regularisation.py`` does (same seed: the same coarse volume); at the finest stage's start the held-out images'
errors (per image) are recorded for the starting volume and after 10, 20 and 40 of its iterations, then the run stops.
The final Δn error that choosing τ leads to is the fixed-weight run's, in ``regularisation_cpu.jsonl``; the rules are
scored offline (``tv_rule_offline.py --coarse-paths``).
"""

from __future__ import annotations

import argparse
import time

from benchmarks._results import append_row, results_file
from benchmarks.regularisation import SCENES, config_for


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--taus", default="1,3,10,30")
    p.add_argument("--probe", type=int, default=40, help="finest-stage iterations to trace")
    p.add_argument("--device", default="cpu")
    a = p.parse_args(argv)

    import napari_fdt.recon.solver as solver_mod
    from napari_fdt import read_acquisition
    from napari_fdt.recon.stage_loop import Verdict

    folder, _ = SCENES[a.scene]
    acq = read_acquisition(folder)
    marks = (0, 10, 20, a.probe)

    class FinestStartProbe:
        trace: list = []

        def at_start(self, rec, work, again, should_stop):
            stage = work.stage
            if stage.index != len(rec.config.stages) - 1:
                return Verdict.GO_ON
            t = time.perf_counter()
            for it in range(0, a.probe + 1):
                if it:
                    rec._set_step_size(work.optimiser, stage, it)
                    progress = (work.base_iteration + it - 1) / max(1, rec.config.total_iterations)  # as the stage's loop
                    rec._step(stage, work.mask, work.optimiser, work.batch_size, work.data_range, progress, False)
                if it in marks:
                    err, each = rec._choice_errors(stage, work.mask)
                    FinestStartProbe.trace.append({"iteration": it, "validation_error": err, "image_errors": each,
                                                   "seconds": time.perf_counter() - t})
            return Verdict.STOPPED
            yield  # (a generator)

        def at_end(self, rec, work, should_stop):
            return Verdict.GO_ON
            yield  # (a generator)

    original = solver_mod.default_choices
    solver_mod.default_choices = lambda: (*original(), FinestStartProbe())
    for tau in (float(x) for x in a.taus.split(",")):
        FinestStartProbe.trace = []
        t0 = time.perf_counter()
        rec = solver_mod.Reconstructor(acq, config_for(f"{tau:g}", {"seed": a.seed}), device=a.device)
        for _ in rec.run():
            pass
        row = {"scene": a.scene, "seed": a.seed, "tau": tau, "device": a.device, "trace": FinestStartProbe.trace,
               "parts_needed": [] if rec.parts_choice is None else rec.parts_choice.needed,
               "wall_s": time.perf_counter() - t0, "date": time.strftime("%Y-%m-%d")}
        append_row(results_file("tv_coarse_paths", a.device), row, a.device)
        print(a.scene, a.seed, "tau", tau, " ".join(f"{r['iteration']}:{r['validation_error']:.5f}" for r in FinestStartProbe.trace),
              f"{row['wall_s']:.0f} s", flush=True)


if __name__ == "__main__":
    main()
