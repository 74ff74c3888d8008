"""Issue 25's question at the finest stage: does a half-set comparison of volumes rank the TV weights as the truth does?

    python -m benchmarks run half_sets SCENE [--seed 0] [--probe 40] [--taus 0,1,3,10,30]

The stages before the finest run at τ_xy 1 (τ_z 0.5). At the finest stage's start the state is kept and, for every τ:
the finest stage runs in full on the training images (its truth error after ``--probe`` iterations and at the end, and
the held-out images' error there), and ``--probe`` iterations on each half of the training images (the other half held
out as the validation images are: it moves only its own positions and gains). Halves: the training images paired with
their nearest neighbour by source position, one of each pair to each half, so that each covers the illumination like
the whole. Criteria (Δn volumes on the acquisition grid, lower is better):

- ``cross``: ‖A(τ) − B(0)‖² + ‖B(τ) − A(0)‖² (noise2noise: each half's unregularised volume as the other's reference);
- ``agree``: ‖A(τ) − B(τ)‖² / (‖A(τ)‖² + ‖B(τ)‖²);
- ``heldout``: the held-out images' error of the full trial at ``--probe`` (today's signal, at the finest stage).

One JSON line per scene and seed (appended to benchmarks/results/half_sets_cpu.jsonl); docs/decisions/tv-weight-choice.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
import torch

from benchmarks._results import append_row, results_file
from benchmarks.scenes import folder_of
from napari_fdt import read_acquisition, read_volume_tiff
from napari_fdt.recon.assess.metrics import relative_delta_n_error
from napari_fdt.recon.assess.validation import split_halves
from napari_fdt.recon.loop.regularisation import selection_stages
from napari_fdt.recon.loop.run_validation import validation
from napari_fdt.recon.loop.stage_loop import Verdict, capture_branch, new_optimiser, restore_branch
from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.config import SolverConfig

OUT = results_file("half_sets", "cpu")


def halves(sources_um: np.ndarray, train: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Split ``train`` (image indices) in two: nearest-neighbour pairs by source (x, y), one of each pair per half
    (:func:`napari_fdt.recon.assess.validation.split_halves` on the training images)."""
    a, b = split_halves(sources_um[train], seed)
    return train[a], train[b]


class Sweep:
    """A choice plugged in at the finest stage's start: runs the study, records it, stops the run."""

    def __init__(self, truth_dn: np.ndarray, taus: list[float], probe: int, seed: int, stage_index: int, full: bool) -> None:
        self.truth, self.taus, self.probe, self.seed = truth_dn, taus, probe, seed
        self.stage_index, self.full = stage_index, full
        self.result: dict = {}

    def _train(self, rec, work, iterations: int, record_at: int | None = None):
        stage = work.stage
        opt = new_optimiser(rec)
        at = None
        for it in range(1, iterations + 1):
            rec._set_step_size(opt, stage, it)
            rec._step(stage, work.mask, opt, work.batch_size, work.data_range,
                      (work.base_iteration + it - 1) / max(1, rec.config.total_iterations))
            if it == record_at:
                at = (rec.delta_n_full(), validation(rec, stage, work.mask)[0])
        return at

    def at_start(self, rec, work, again, should_stop):
        if work.stage.index != self.stage_index:
            return Verdict.GO_ON
        start = capture_branch(rec)
        held0 = rec._held_out.clone()
        train = np.flatnonzero(~held0.cpu().numpy())
        half_a, half_b = halves(rec.initial_sources_um, train, self.seed)
        weights = rec.loss_weights
        rows = []
        vols: dict[tuple[str, float], np.ndarray] = {}
        for tau in self.taus:
            rec.loss_weights = dataclasses.replace(weights, tv_xy=tau, tv_z=tau / 2)
            t = time.perf_counter()
            restore_branch(rec, start)
            dn_probe, val_probe = self._train(rec, work, work.stage.iterations if self.full else self.probe, record_at=self.probe)
            final = relative_delta_n_error(rec.delta_n_full(), self.truth) if self.full else None
            row = {"tau": tau, "truth_probe": relative_delta_n_error(dn_probe, self.truth), "truth_final": final,
                   "heldout_probe": val_probe, "full_s": time.perf_counter() - t}
            for name, other in (("A", half_b), ("B", half_a)):
                restore_branch(rec, start)
                rec._held_out = held0.clone()
                rec._held_out[torch.as_tensor(other, device=rec.device)] = True
                self._train(rec, work, self.probe)
                vols[(name, tau)] = rec.delta_n_full()
                rec._held_out = held0.clone()
            rows.append(row)
            print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
        a0, b0 = vols[("A", self.taus[0])], vols[("B", self.taus[0])]
        for row in rows:
            a, b = vols[("A", row["tau"])], vols[("B", row["tau"])]
            row["cross"] = float(((a - b0) ** 2).sum() + ((b - a0) ** 2).sum())
            row["agree"] = float(((a - b) ** 2).sum() / ((a**2).sum() + (b**2).sum()))
        restore_branch(rec, start)
        rec.loss_weights = weights
        self.result = {"rows": rows, "halves": [len(half_a), len(half_b)]}
        return Verdict.STOPPED
        yield

    def at_end(self, rec, work, should_stop):
        return Verdict.GO_ON
        yield


def reference_finals(scene: str, seed: int) -> dict[float, float]:
    """Final relative Δn errors of full runs at fixed τ (τ_z = τ/2), the latest row per τ, from the regularisation
    benchmark's results (benchmarks/results/regularisation_cpu.jsonl)."""
    finals: dict[float, float] = {}
    path = results_file("regularisation", "cpu")
    for line in path.read_text().splitlines():
        r = json.loads(line)
        if r["scene"] == scene and r["setting"] != "auto" and r.get("config_overrides", {}).get("seed", 0) == seed:
            finals[float(r["setting"])] = r["relative_delta_n_error"]
    return finals


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--probe", type=int, default=40)
    ap.add_argument("--taus", default="0,1,3,10,30")
    ap.add_argument("--at", choices=("finest", "selection"), default="finest",
                    help="where: the finest stage's start (stages before at τ 1; the stage run in full per τ), or the "
                         "selection stage's start as the automatic choice runs (the stages before without TV; probes only: "
                         "the final errors of runs at each τ come from benchmarks/results/regularisation_cpu.jsonl)")
    args = ap.parse_args()
    folder = folder_of(args.scene)
    acq = read_acquisition(folder)
    truth, _ = read_volume_tiff(folder / "ground_truth_ri.tif")
    tau0 = 1.0 if args.at == "finest" else 0.0
    cfg = SolverConfig.from_dict({**SolverConfig().to_dict(), "seed": args.seed, "tv_xy_weight": tau0, "tv_z_weight": tau0 / 2,
                                  "early_stopping": "off"})
    rec = Reconstructor(acq, cfg, device="cpu")
    at = len(cfg.stages) - 1 if args.at == "finest" else selection_stages(cfg)[0]
    sweep = Sweep(truth - acq.optics.n_background, [float(t) for t in args.taus.split(",")], args.probe, args.seed, at,
                  args.at == "finest")
    rec.choices = [sweep, *rec.choices]
    t = time.perf_counter()
    for _ in rec.run():
        pass
    rows = sweep.result["rows"]
    if args.at == "selection":  # the final errors of full runs at each τ (seed 0's sweep of the regularisation benchmark)
        finals = reference_finals(args.scene, args.seed)
        rows = [dict(r, truth_final=finals[r["tau"]]) for r in rows if r["tau"] in finals]
    best = min(rows, key=lambda r: r["truth_final"])
    summary = {"scene": args.scene, "seed": args.seed, "at": args.at, "probe": args.probe, "halves": sweep.result["halves"],
               "best_final": best["tau"], "wall_s": round(time.perf_counter() - t, 1), "date": time.strftime("%Y-%m-%d")}
    for crit in ("cross", "agree", "heldout_probe", "truth_probe"):
        pick = min(rows, key=lambda r: r[crit])
        summary[f"pick_{crit}"] = pick["tau"]
        summary[f"ratio_{crit}"] = round(pick["truth_final"] / best["truth_final"], 3)
    line = {**summary, "rows": rows}
    print(json.dumps(summary), flush=True)
    append_row(OUT, line)


if __name__ == "__main__":
    main()
