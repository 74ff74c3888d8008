"""The choice of the "auto" TV weights inside the run: at the selection stage every weight of the TV path trains from
the stage's starting state and the held-out images pick one (the rule is :mod:`napari_fdt.recon.regularisation`'s).
The stages before the selection stage run without TV (the weight is not known yet). Where the winner is no TV, the run
goes on from the winner's state (only the losing trials' iterations were extra); otherwise the stages before run again
with the chosen weight, what the choice changed.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Generator

import torch

from napari_fdt.recon.phases import TV_CHOICE, probe_iterations
from napari_fdt.recon.regularisation import TV_PATH, TVChoice, candidate_weights, pick, tried_enough
from napari_fdt.recon.run_validation import validation
from napari_fdt.recon.snapshot import Snapshot, take_snapshot
from napari_fdt.recon.stages import Stage
from napari_fdt.recon.validation import BestIterate

if TYPE_CHECKING:
    from napari_fdt.recon.solver import Reconstructor

__all__ = ["TrialsOutcome", "choose_tv", "capture_branch", "restore_branch"]


@dataclass
class TrialsOutcome:
    """What follows the TV trials: ``redo`` (the stages before run again with the chosen weights: the state is then
    a trial's), else the stage goes on from the winner's state with its volume ``optimiser`` after ``iterations``
    (the probe). ``t0``: the stage's clock start moved past the consumer's pauses; ``losers_s``: the losing trials'
    seconds."""

    redo: bool
    optimiser: torch.optim.Optimizer | None
    iterations: int
    t0: float
    losers_s: float


def choose_tv(rec: Reconstructor, stage: Stage, mask: torch.Tensor | None, batch_size: int, data_range: float, global_it: int,
              t0: float, best: BestIterate, should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, TrialsOutcome | None]:
    """Try the weights of the TV path from the stage's starting state (volume, calibration and its optimiser, batch
    order: the trials differ only by their weight), each for :func:`probe_iterations` of the stage's iterations; set
    ``rec.tv_choice`` and the loss weights to the one the held-out images prefer. Where the stages before ran with
    that weight (or there were none) the state is left at the end of the winner's trial and the plan's stages before
    are dropped; otherwise the outcome asks for the stages before again (:attr:`TrialsOutcome.redo`). Yields a
    snapshot after each weight (phase "tv_choice"); stops trying larger weights once :func:`tried_enough` (the plan's
    trial phase is then cut to the weights tried). ``t0``: the stage's clock start.
    Returns None when stopped (cancelled) meanwhile; stopped or closed, the state is the stage's start again."""
    cfg = rec.config
    n_probe = probe_iterations(stage.iterations)
    start = capture_branch(rec)
    weights = rec.loss_weights
    trials: list[dict] = []
    ends: list[dict[str, Any]] = []
    rec._phase_index = rec.plan.index(TV_CHOICE, stage.index, trials=True)
    finished = False
    try:
        for k, tau in enumerate(TV_PATH):
            if tried_enough(trials):  # past the minimum the error only rises: the larger weights would not be picked
                rec._revise_plan(rec.plan.with_iterations(rec._phase_index, len(trials) * n_probe))
                break
            t1 = time.perf_counter()
            restore_branch(rec, start)
            xy, z = candidate_weights(cfg, tau)
            rec.loss_weights = dataclasses.replace(weights, tv_xy=xy, tv_z=z)
            vol_opt = torch.optim.Adam([rec.volume.x], lr=cfg.lr_ri, betas=(0.9, 0.99))
            for it in range(1, n_probe + 1):
                if rec._stop_requested(should_stop):
                    return None
                rec._set_step_size(vol_opt, stage, it)
                terms, train_error = rec._step(stage, mask, vol_opt, batch_size, data_range,
                                               (global_it + it - 1) / max(1, cfg.total_iterations), it == n_probe)
            err, each = validation(rec, stage, mask, per_image=True)
            ends.append({**capture_branch(rec), "vol_opt": copy.deepcopy(vol_opt.state_dict())})
            trials.append({"tau": tau, "tv_xy_weight": xy, "tv_z_weight": z, "validation_error": err, "image_errors": each,
                           "seconds": time.perf_counter() - t1})
            snap = take_snapshot(rec, stage, n_probe, global_it + n_probe, terms, t0, False, err, train_error, trial=k)
            paused = time.perf_counter()
            yield snap
            t0 += time.perf_counter() - paused  # time spent by the consumer is not the solver's
        finished = True
    finally:
        if not finished:  # stopped or closed: back to the stage's start, nothing chosen (a new run chooses again)
            restore_branch(rec, start)
            rec.loss_weights = weights
    win = pick(trials)
    k = trials.index(win)
    rec.loss_weights = dataclasses.replace(weights, tv_xy=win["tv_xy_weight"], tv_z=win["tv_z_weight"])
    losers_s = sum(t["seconds"] for j, t in enumerate(trials) if j != k)
    rec.tv_choice = TVChoice(win["tv_xy_weight"], win["tv_z_weight"], stage=stage.index, probe_iterations=n_probe,
                             trials=trials, seconds=sum(t["seconds"] for t in trials))
    if stage.index > 0 and (win["tv_xy_weight"], win["tv_z_weight"]) != (weights.tv_xy, weights.tv_z):
        return TrialsOutcome(True, None, 0, t0, losers_s)
    restore_branch(rec, ends[k])
    vol_opt = torch.optim.Adam([rec.volume.x], lr=cfg.lr_ri, betas=(0.9, 0.99))
    vol_opt.load_state_dict(ends[k]["vol_opt"])
    rec._revise_plan(rec.plan.keeping_the_stages_before(stage.index, n_probe))
    if cfg.early_stopping != "off" and win["validation_error"] is not None:  # the winner's end is a candidate iterate
        best.update(n_probe, win["validation_error"], rec._capture)
    return TrialsOutcome(False, vol_opt, n_probe, t0, losers_s)


def capture_branch(rec: Reconstructor) -> dict[str, Any]:
    """A full copy of what training changes (volume, calibration and its optimiser, batch order), to start
    several candidates from one state."""
    return {**rec._capture(), "cal_opt": copy.deepcopy(rec.calibration.optimiser.state_dict()),
            "batches": copy.deepcopy(rec.batches.state_dict())}


def restore_branch(rec: Reconstructor, state: dict[str, Any]) -> None:
    """Return to a :func:`capture_branch` (copies again, so the state can be restored more than once)."""
    rec._restore(state, keep_bookkeeping=True)
    rec.calibration.optimiser.load_state_dict(copy.deepcopy(state["cal_opt"]))
    rec.batches.load_state_dict(copy.deepcopy(state["batches"]))
