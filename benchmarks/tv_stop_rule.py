"""The TV trials' early stop against its noise: every weight of the path tried, then the choice each stop rule makes.

Question (issue 47, item 3): the "auto" TV choice tries τ_xy 1, 3, 10, 30, 100 in turn and stopped at the first weight
significantly worse than the best so far, "significantly" meaning one paired standard error. On an unseen sparse
scene a rise of 0.2 % (inside the held-out images' paired spread) stopped it at τ 1, where going on picked τ 10 and a
volume 18 % better. How often does the stop decide by noise, and what does a stricter stop change?

``run``: each scene and seed's default run up to its TV choice (the pupil's pilot, the stages before the selection
stage, then *every* weight of the path, no early stop), its trials (with each held-out image's error) as one row of
``benchmarks/results/tv_stop_rule_cpu.jsonl``. ``table``: for each row the stop's z (the stopping weight's mean paired
rise over its standard error) and the weight chosen with no stop, the 1-SE stop (the rule until 2026-11-27) and the
Student's t(0.975, n − 1) stop (the rule since, the model parts' noise rule).

    python -m benchmarks run tv_stop_rule run --scenes sample,beads,cells,deep,letters128 --seeds 0,1,2
    python -m benchmarks run tv_stop_rule table
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from benchmarks._results import append_row, read_rows, results_file

RESULTS = results_file("tv_stop_rule")


def _z(trial: dict, best: dict) -> float:
    d = np.asarray(trial["image_errors"], dtype=np.float64) - np.asarray(best["image_errors"], dtype=np.float64)
    return float(d.mean() / (d.std(ddof=1) / np.sqrt(d.size))) if d.size > 1 and d.std(ddof=1) > 0 else float("inf")


def choose(trials: list[dict], stop_se: float | str | None) -> tuple[float, int]:
    """(the weight :func:`~napari_fdt.recon.loop.regularisation.pick` takes from the trials a stop rule lets run, how many
    ran): the trials in order until one has a larger weight than the best so far and a rise of more than ``stop_se``
    paired standard errors ("t": Student's t(0.975, n − 1), today's rule; None: no stop)."""
    from napari_fdt.recon.loop.model_parts import standard_errors
    from napari_fdt.recon.loop.regularisation import pick

    tried: list[dict] = []
    for t in trials:
        tried.append(t)
        best = min(tried, key=lambda x: x["validation_error"])
        k = standard_errors(len(t["image_errors"])) if stop_se == "t" else stop_se
        if k is not None and len(tried) >= 2 and t["tau"] > best["tau"] and _z(t, best) > k:
            break
    return pick(tried)["tau"], len(tried)


def run(scenes: list[str], seeds: list[int]) -> None:
    import napari_fdt.recon.choices.tv_search as tv_search
    from benchmarks.scenes import folder_of, make_scenes
    from napari_fdt import read_acquisition
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig

    make_scenes([s for s in scenes if s != "sample"])
    tv_search.tried_enough = lambda trials, *a, **k: False  # every weight of the path (this process only)
    for scene in scenes:
        acq = read_acquisition(folder_of(scene))
        for seed in seeds:
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rec = Reconstructor(acq, SolverConfig(seed=seed), device="cpu")
                for _ in rec.run(should_stop=lambda: rec.tv_choice is not None):
                    pass
            choice = rec.tv_choice
            row = {"scene": scene, "seed": seed, "stage": choice.stage, "probe_iterations": choice.probe_iterations,
                   "trials": [{k: t[k] for k in ("tau", "validation_error", "image_errors", "seconds")} for t in choice.trials],
                   "wall_s": time.perf_counter() - t0}
            append_row(RESULTS, row)
            print(f"{scene} seed {seed}: " + ", ".join(f"τ {t['tau']:g} {t['validation_error']:.5f}" for t in choice.trials)
                  + f" ({row['wall_s']:.0f} s)", flush=True)


def table() -> None:
    print("| scene | seed | held-out images | held-out errors τ 1 / 3 / 10 / 30 / 100 | z of each against the best | no stop | "
          "1-SE stop (tried) | t stop (tried) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in read_rows(RESULTS):
        trials = r["trials"]
        best = min(trials, key=lambda t: t["validation_error"])
        errs = " / ".join(f"{t['validation_error']:.4f}" for t in trials)
        zs = " / ".join("—" if t is best else f"{_z(t, best):.1f}" for t in trials)
        none, one, two = choose(trials, None), choose(trials, 1.0), choose(trials, "t")
        print(f"| {r['scene']} | {r['seed']} | {len(best['image_errors'])} | {errs} | {zs} | {none[0]:g} | {one[0]:g} ({one[1]}) | "
              f"{two[0]:g} ({two[1]}) |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--scenes", default="sample,beads,cells,deep,letters128")
    r.add_argument("--seeds", default="0,1,2")
    sub.add_parser("table")
    args = ap.parse_args()
    if args.cmd == "run":
        run(args.scenes.split(","), [int(s) for s in args.seeds.split(",")])
    else:
        table()


if __name__ == "__main__":
    main()
