"""The choice of the "auto" TV weights in a run: the pilot that runs the stages up to the selection stage, the trial of
every weight of the TV path there from one state, and the copies of the training state the trials start from (the
rule that picks the weight is :mod:`napari_fdt.recon.regularisation`'s).
"""

from __future__ import annotations

import copy
import dataclasses
import time
from typing import TYPE_CHECKING, Any, Callable, Generator, Iterator

import torch

from napari_fdt.recon.phases import TV_CHOICE, probe_iterations
from napari_fdt.recon.regularisation import TV_PATH, TVChoice, candidate_weights, pick, tried_enough
from napari_fdt.recon.run_validation import validation
from napari_fdt.recon.snapshot import Snapshot, take_snapshot
from napari_fdt.recon.stages import Stage

if TYPE_CHECKING:
    from napari_fdt.recon.solver import Reconstructor

__all__ = ["pilot", "choose_tv", "capture_branch", "restore_branch"]


def pilot(rec: Reconstructor, should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, bool]:
    """Choose the "auto" TV weights: run the stages before the selection stage as the run would (TV off), try the
    weights at the selection stage (:func:`choose_tv`), then return to the initial state with the weights set, so
    that the run equals one given them as numbers from its first stage on. Yields the snapshots meanwhile (phase
    "tv_choice"); returns False when cancelled meanwhile (closed or failed: back to the initial state too)."""
    t0 = time.perf_counter()
    rec._piloting, finished = True, False
    try:
        for snap in rec._run_stages(should_stop, None):  # ends at the selection stage, once the weights are tried
            paused = time.perf_counter()
            yield snap
            t0 += time.perf_counter() - paused  # the consumer's time is not the pilot's
        finished = True
    finally:
        rec._piloting = False
        if not finished:
            rec._restart()
    choice = rec.tv_choice
    rec._restart()
    if choice is None:  # cancelled
        return False
    choice.seconds = time.perf_counter() - t0
    rec.tv_choice = choice
    rec.loss_weights = dataclasses.replace(rec.loss_weights, tv_xy=choice.tv_xy_weight, tv_z=choice.tv_z_weight)
    rec.elapsed_s = choice.seconds  # the pilot's time is the run's
    return True


def choose_tv(rec: Reconstructor, stage: Stage, mask: torch.Tensor | None, batch_size: int, data_range: float, global_it: int,
              should_stop: Callable[[], bool] | None) -> Iterator[Snapshot]:
    """Try every weight of the TV path from the stage's starting state and set ``rec.tv_choice`` to the one the
    held-out images prefer (:mod:`napari_fdt.recon.regularisation`); left None when stopped (cancelled) meanwhile.
    Yields a snapshot after each weight; stops trying larger weights once :func:`tried_enough` (the plan's trial phase
    is then cut to the weights tried). The state is then a trial's: the pilot (:func:`pilot`) starts the run again."""
    cfg = rec.config
    t0 = time.perf_counter()
    n_probe = probe_iterations(stage.iterations)
    start = capture_branch(rec)
    trials: list[dict] = []
    rec._phase_index = rec.plan.index(TV_CHOICE, stage.index, trials=True)
    for k, tau in enumerate(TV_PATH):
        if tried_enough(trials):  # past the minimum the error only rises: the larger weights would not be picked
            rec._revise_plan(rec.plan.with_iterations(rec._phase_index, len(trials) * n_probe))
            break
        t1 = time.perf_counter()
        restore_branch(rec, start)
        xy, z = candidate_weights(cfg, tau)
        rec.loss_weights = dataclasses.replace(rec.loss_weights, tv_xy=xy, tv_z=z)
        vol_opt = torch.optim.Adam([rec.volume.x], lr=cfg.lr_ri, betas=(0.9, 0.99))
        for it in range(n_probe):
            if rec._stop_requested(should_stop):
                return
            terms, train_error = rec._step(stage, mask, vol_opt, batch_size, data_range,
                                           (global_it + it) / max(1, cfg.total_iterations), it == n_probe - 1)
        err, each = validation(rec, stage, mask, per_image=True)
        trials.append({"tau": tau, "tv_xy_weight": xy, "tv_z_weight": z, "validation_error": err, "image_errors": each,
                       "seconds": time.perf_counter() - t1})
        snap = take_snapshot(rec, stage, n_probe, global_it + n_probe, terms, t1, False, err, train_error, trial=k)
        rec.elapsed_s += time.perf_counter() - t1  # (the pilot sets the run's time when it ends)
        yield snap
    win = pick(trials)
    rec.tv_choice = TVChoice(win["tv_xy_weight"], win["tv_z_weight"], stage=stage.index, probe_iterations=n_probe,
                             trials=trials, seconds=time.perf_counter() - t0)


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
