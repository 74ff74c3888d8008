"""The choice of the "auto" TV weights inside the run: at the selection stage every weight of the TV path trains from
the stage's starting state and the held-out images pick one (the rule is :mod:`napari_fdt.recon.loop.regularisation`'s).
The stages before the selection stage run at the path's smallest weight (the weight is not known yet). Where that weight
wins, the run goes on from the winner's state (only the losing trials' iterations were extra); otherwise the stages before run again
with the chosen weight, what the choice changed.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from typing import TYPE_CHECKING, Any, Callable, Generator

from napari_fdt.recon.loop.phases import TV_CHOICE, probe_iterations
from napari_fdt.recon.loop.regularisation import TV_PATH, TVChoice, candidate_weights, pick, tried_enough
from napari_fdt.recon.loop.run_validation import validation
from napari_fdt.recon.loop.snapshot import Snapshot, take_snapshot
from napari_fdt.recon.loop.stage_loop import StageWork, Verdict, capture_branch, new_optimiser, restore_branch

if TYPE_CHECKING:
    from napari_fdt.recon.loop.interface import Run

__all__ = ["choose_tv"]


def choose_tv(rec: Run, work: StageWork, should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, Verdict]:
    """Try the weights of the TV path from the stage's starting state (volume, calibration and its optimiser, batch
    order: the trials differ only by their weight), each for :func:`probe_iterations` of the stage's iterations; set
    ``rec.tv_choice`` and the loss weights to the one the held-out images prefer. Where the stages before ran with
    that weight (or there were none) the stage goes on from the end of the winner's trial (``work`` takes its volume
    optimiser and iterations; the plan drops the run's stages before) and GO_ON is returned; otherwise
    FROM_FIRST_STAGE (the caller sets the run back). Yields a snapshot after each weight (phase "tv_choice"); stops
    trying larger weights once :func:`tried_enough` (the plan's trial phase is then cut to the weights tried).
    Stopped (STOPPED) or closed, the state is the stage's start again and nothing is chosen."""
    cfg, stage = rec.config, work.stage
    n_probe = probe_iterations(stage.iterations)
    start = capture_branch(rec)
    weights = rec.loss_weights
    trials: list[dict] = []
    ends: list[dict[str, Any]] = []
    rec._phase_index = rec.plan.index(TV_CHOICE, stage.index, trials=True)
    finished = False
    try:
        for k, tau in enumerate(TV_PATH):
            t1 = time.perf_counter()
            restore_branch(rec, start)
            xy, z = candidate_weights(cfg, tau)
            rec.loss_weights = dataclasses.replace(weights, tv_xy=xy, tv_z=z)
            vol_opt = new_optimiser(rec)
            for it in range(1, n_probe + 1):
                if rec._stop_requested(should_stop):
                    return Verdict.STOPPED
                rec._set_step_size(vol_opt, stage, it)
                terms, train_error = rec._step(stage, work.mask, vol_opt, work.batch_size, work.data_range,
                                               (work.base_iteration + it - 1) / max(1, cfg.total_iterations), it == n_probe)
            err, each = validation(rec, stage, work.mask, per_image=True)
            ends.append({**capture_branch(rec), "vol_opt": copy.deepcopy(vol_opt.state_dict())})
            trials.append({"tau": tau, "tv_xy_weight": xy, "tv_z_weight": z, "validation_error": err, "image_errors": each,
                           "seconds": time.perf_counter() - t1})
            # past the minimum the error only rises: the larger weights would not be picked
            enough = tried_enough(trials) and k + 1 < len(TV_PATH)
            if enough:  # the last trial: its snapshot shows the plan cut to the weights tried
                rec._revise_plan(rec.plan.with_iterations(rec._phase_index, len(trials) * n_probe))
            yield from work.hand_over(take_snapshot(rec, stage, n_probe, work.base_iteration + n_probe, terms, work.t0, False,
                                                    err, train_error, trial=k))
            if enough:
                break
        finished = True
    finally:
        if not finished:  # stopped or closed: back to the stage's start, nothing chosen (a new run chooses again)
            restore_branch(rec, start)
            rec.loss_weights = weights
    win = pick(trials)
    k = trials.index(win)
    rec.loss_weights = dataclasses.replace(weights, tv_xy=win["tv_xy_weight"], tv_z=win["tv_z_weight"])
    rec.tv_choice = TVChoice(win["tv_xy_weight"], win["tv_z_weight"], stage=stage.index, probe_iterations=n_probe,
                             trials=trials, seconds=sum(t["seconds"] for t in trials))
    if stage.index > 0 and (win["tv_xy_weight"], win["tv_z_weight"]) != (weights.tv_xy, weights.tv_z):
        rec._revise_plan(rec.plan.with_stages_again(stage.index))  # the stages before, again with the winner
        return Verdict.FROM_FIRST_STAGE
    rec._revise_plan(rec.plan.tv_chosen())  # the stages before are kept: the plan's top loses the TV's share
    restore_branch(rec, ends[k])
    work.optimiser = new_optimiser(rec)
    work.optimiser.load_state_dict(ends[k]["vol_opt"])
    work.done = n_probe
    work.record.choice_s += sum(t["seconds"] for j, t in enumerate(trials) if j != k)
    if cfg.early_stopping != "off" and win["validation_error"] is not None:  # the winner's end is a candidate iterate
        work.best.update(n_probe, win["validation_error"], rec._capture)
    return Verdict.GO_ON
