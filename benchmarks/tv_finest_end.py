"""Issue 25 experiment: at the finest stage's end, do a few more iterations at the neighbouring TV weights separate on
the held-out images where the selection stage's trials cannot?

    python -m benchmarks run tv_finest_end SCENE --seed S [--fraction 0.3]   # → benchmarks/results/tv_finest_end_cpu.jsonl

Runs the defaults (TV "auto"). At the finest stage's end (after its best iterate is restored) the state is captured
and the finest stage continues ``fraction`` of its iterations from it, once at each of the chosen weight (the control),
the next larger weight of the path and the next smaller one; each continuation's held-out errors (per image) and
relative Δn error against the truth are recorded; then the run ends as the defaults do. A prototype: the rules are
scored offline from the rows.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import time

from benchmarks._results import append_row, results_file
from benchmarks.regularisation import SCENES, config_for


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fraction", type=float, default=0.3)
    p.add_argument("--device", default="cpu")
    p.add_argument("--at", choices=("end", "start"), default="end",
                   help="end: continue `fraction` of the finest stage from its end; start: run the whole finest stage "
                        "again from its start at each weight, the held-out errors traced every 20 iterations")
    p.add_argument("--coarse-tau", type=float, default=None,
                   help="run the stages before the finest at this fixed τ_xy (τ_z = τ/2); with --at start the finest "
                        "stage is then run at τ_xy 1, 3 and 10 from their end")
    a = p.parse_args(argv)

    import napari_fdt.recon.solver as solver_mod
    from napari_fdt import read_acquisition, read_volume_tiff
    from napari_fdt.recon.metrics import relative_delta_n_error
    from napari_fdt.recon.regularisation import TV_PATH, candidate_weights
    from napari_fdt.recon.stage_loop import Verdict, capture_branch, new_optimiser, restore_branch

    folder, _ = SCENES[a.scene]
    acq = read_acquisition(folder)
    truth, _ = read_volume_tiff(folder / "ground_truth_ri.tif")
    true_dn = truth - acq.optics.n_background
    cfg = config_for("auto" if a.coarse_tau is None else f"{a.coarse_tau:g}", {"seed": a.seed})
    probes: list[dict] = []

    class FinestEndProbe:
        start_state = None

        def at_start(self, rec, work, again, should_stop):
            if work.stage.index == len(rec.config.stages) - 1 and not again:
                FinestEndProbe.start_state = capture_branch(rec)
            return Verdict.GO_ON
            yield

        def at_end(self, rec, work, should_stop):
            stage = work.stage
            if stage.index != len(rec.config.stages) - 1 or (rec.tv_choice is None and a.coarse_tau is None):
                return Verdict.GO_ON
                yield
            probes.clear()
            k = max(1, round(a.fraction * stage.iterations)) if a.at == "end" else stage.iterations
            start = capture_branch(rec)
            branch_from = start if a.at == "end" else FinestEndProbe.start_state
            opt_state = copy.deepcopy(work.optimiser.state_dict())
            weights = rec.loss_weights
            if a.coarse_tau is None:
                tau_c = rec.tv_choice.tv_xy_weight
                i = min(range(len(TV_PATH)), key=lambda j: abs(TV_PATH[j] - tau_c))
                taus = [tau_c] + [TV_PATH[j] for j in (i + 1, i - 1) if 0 <= j < len(TV_PATH)]
            else:
                tau_c, taus = a.coarse_tau, [1.0, 3.0, 10.0]
            err0, each0 = rec._choice_errors(stage, work.mask)
            probes.append({"tau": tau_c, "iterations": 0, "validation_error": err0, "image_errors": each0,
                           "relative_delta_n_error": relative_delta_n_error(rec.delta_n_full(), true_dn)})
            for tau in taus:
                restore_branch(rec, branch_from)
                xy, z = candidate_weights(rec.config, tau) if a.coarse_tau is None else (tau, tau / 2)
                rec.loss_weights = dataclasses.replace(weights, tv_xy=xy, tv_z=z)
                opt = new_optimiser(rec)
                if a.at == "end":
                    opt.load_state_dict(copy.deepcopy(opt_state))
                t = time.perf_counter()
                trace = []
                for it in range(1, k + 1):
                    rec._set_step_size(opt, stage, stage.iterations if a.at == "end" else it)
                    rec._step(stage, work.mask, opt, work.batch_size, work.data_range, 1.0, False)
                    if a.at == "start" and (it % 20 == 0 or it == k):
                        e, _ = rec._choice_errors(stage, work.mask)
                        trace.append((it, e, relative_delta_n_error(rec.delta_n_full(), true_dn)))
                err, each = rec._choice_errors(stage, work.mask)
                probes.append({"tau": tau, "iterations": k, "validation_error": err, "image_errors": each,
                               "relative_delta_n_error": relative_delta_n_error(rec.delta_n_full(), true_dn),
                               "trace": trace, "seconds": time.perf_counter() - t})
            restore_branch(rec, start)
            rec.loss_weights = weights
            return Verdict.GO_ON
            yield  # (a generator)

    original = solver_mod.default_choices
    solver_mod.default_choices = lambda: (*original(), FinestEndProbe())
    t0 = time.perf_counter()
    rec = solver_mod.Reconstructor(acq, cfg, device=a.device)
    for _ in rec.run():
        pass
    row = {"scene": a.scene, "seed": a.seed, "at": a.at, "fraction": a.fraction, "device": a.device,
           "coarse_tau": a.coarse_tau, "tau_chosen": None if rec.tv_choice is None else rec.tv_choice.tv_xy_weight,
           "relative_delta_n_error": relative_delta_n_error(rec.delta_n_full(), true_dn),
           "parts_needed": [] if rec.parts_choice is None else rec.parts_choice.needed,
           "finest_iterations": rec.config.stages[-1].iterations, "probes": probes, "wall_s": time.perf_counter() - t0,
           "date": time.strftime("%Y-%m-%d")}
    append_row(results_file("tv_finest_end", a.device), row, a.device)
    print(a.scene, a.seed, "chosen", row["tau_chosen"], "coarse", a.coarse_tau, "dn %.3f" % row["relative_delta_n_error"])
    for pr in probes:
        print("   tau %-5g +%3d it  val %.5f  dn %.3f" % (pr["tau"], pr["iterations"], pr["validation_error"], pr["relative_delta_n_error"]))
        for it, e, dn in pr.get("trace", []):
            print("        it %4d  val %.5f  dn %.3f" % (it, e, dn))


if __name__ == "__main__":
    main()
