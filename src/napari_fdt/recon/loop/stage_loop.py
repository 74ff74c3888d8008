"""One stage of a run: its training state (:class:`StageWork`), its steps (:func:`iterate`), and the choices plugged in
around them (:func:`train_stage`).

A *choice* (:class:`Choice`; :mod:`napari_fdt.recon.choices.plugged` has the TV weights' and the model parts') is called at
the start of every stage and at its end. It may do nothing, try candidates and go on from the winner, or answer a
:class:`Verdict` that sends the run elsewhere: the stage again from its start, every stage again from the first, or
stop. The loop itself is the algorithm only: batch, prediction, loss, step, a snapshot every ``snapshot_every``.
"""

from __future__ import annotations

import copy
import enum
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Generator, Protocol, Sequence

import torch

from napari_fdt.recon.assess.validation import BestIterate
from napari_fdt.recon.calibration.adam import Adam
from napari_fdt.recon.loop.run_validation import end_on_best, track_validation
from napari_fdt.recon.loop.snapshot import Snapshot, StageRecord, take_snapshot
from napari_fdt.recon.problem.stages import Stage

if TYPE_CHECKING:
    from napari_fdt.recon.loop.interface import Run

__all__ = ["Verdict", "StageWork", "Choice", "train_stage", "iterate", "new_optimiser", "capture_branch", "restore_branch"]


class Verdict(enum.Enum):
    """What a choice (or a stage) tells the run: go on; stopped (cancelled); this stage again from its start (the
    stage's model changed); every stage again from the first (the choice changed what they do)."""

    GO_ON = "go on"
    STOPPED = "stopped"
    STAGE_AGAIN = "stage again"
    FROM_FIRST_STAGE = "from the first stage"


def new_optimiser(rec: Run) -> torch.optim.Optimizer:
    """The RI grid's Adam optimiser (new at every stage: its moments belong to the voxels the resampling replaces)."""
    return Adam([rec.volume.x], lr=rec.config.lr_ri, betas=(0.9, 0.99))


@dataclass
class StageWork:
    """A stage being trained. ``done``: its iterations done (a TV trial's winner may have done the first ones);
    ``base_iteration``: the run's iterations before the stage (``global_iteration`` counts on from it); ``t0``: the
    stage's clock start, moved on by the time consumers hold a snapshot; ``terms`` / ``train_error`` /
    ``validation_error``: the last iteration's loss terms and errors; ``choosing``: what the choices mark for the
    stage's end, e.g. the state to start it again from."""

    stage: Stage
    mask: torch.Tensor | None
    optimiser: torch.optim.Optimizer
    batch_size: int
    data_range: float
    record: StageRecord
    best: BestIterate
    base_iteration: int
    t0: float = field(default_factory=time.perf_counter)
    done: int = 0
    terms: dict[str, Any] = field(default_factory=dict)
    train_error: float | None = None
    validation_error: float | None = None
    choosing: dict[str, Any] = field(default_factory=dict)
    #: resumed from a checkpoint written inside the stage: its start (validation, the choices) has been done
    resumed: bool = False

    @property
    def global_iteration(self) -> int:
        return self.base_iteration + self.done

    def hand_over(self, snap: Snapshot) -> Generator[Snapshot, None, None]:
        """Yield ``snap``; the consumer's time is not the solver's (the clock start moves on by it)."""
        paused = time.perf_counter()
        yield snap
        self.t0 += time.perf_counter() - paused


class Choice(Protocol):
    """A choice plugged into the loop. Both calls are generators (they may yield snapshots of their trials) that
    return a :class:`Verdict`; ``again``: the stage's passes before this one (a stage run again from its start)."""

    def at_start(self, rec: Run, work: StageWork, again: int,
                 should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, Verdict]: ...

    def at_end(self, rec: Run, work: StageWork, should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, Verdict]: ...


def train_stage(rec: Run, work: StageWork, choices: Sequence[Choice],
                should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, Verdict]:
    """The stage: the choices at its start, its iterations (:func:`iterate`), the choices at its end; again from its
    start while a choice says :attr:`Verdict.STAGE_AGAIN`. Returns GO_ON when the stage is complete."""
    again = 0
    while True:
        if again or not work.resumed:  # (a stage resumed inside it had its start before the checkpoint)
            if len(rec.validation_indices) and rec.config.early_stopping != "off":
                # The stage's starting volume is a candidate too: a stage that only makes the held-out images worse
                # ends where it began (from stage 0 on: never a volume that explains them worse than no object).
                track_validation(rec, work.stage, work.mask, work.best, 0)
            for choice in choices:
                verdict = yield from choice.at_start(rec, work, again, should_stop)
                if verdict is not Verdict.GO_ON:
                    return verdict
        if not (yield from iterate(rec, work, should_stop)):
            return Verdict.STOPPED
        verdict = Verdict.GO_ON
        for choice in choices:
            verdict = yield from choice.at_end(rec, work, should_stop)
            if verdict is not Verdict.GO_ON:
                break
        if verdict is not Verdict.STAGE_AGAIN:
            return verdict
        again += 1


def iterate(rec: Run, work: StageWork, should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, bool]:
    """The stage's remaining iterations: batch, prediction, loss, step (:meth:`Reconstructor._step`), a snapshot every
    ``snapshot_every`` (early stopping may end the stage there); then back to the best iterate where the last is worse
    (:func:`~napari_fdt.recon.loop.run_validation.end_on_best`). False when stopped (cancelled)."""
    cfg, stage = rec.config, work.stage
    for it in range(work.done + 1, stage.iterations + 1):
        if rec._stop_requested(should_stop):
            return False
        snapshot_due = it == stage.iterations or it % cfg.snapshot_every == 0
        rec._set_step_size(work.optimiser, stage, it)
        progress = (work.base_iteration + it - 1) / max(1, cfg.total_iterations)
        work.terms, err = rec._step(stage, work.mask, work.optimiser, work.batch_size, work.data_range, progress, snapshot_due)
        work.train_error = err if snapshot_due else work.train_error
        work.done = it
        if it == stage.iterations:
            break
        if it % cfg.snapshot_every == 0:
            val = track_validation(rec, stage, work.mask, work.best, it)
            stalled = cfg.early_stopping == "stop" and work.best.stalled(cfg.early_stopping_patience)
            if not stalled:  # a checkpoint inside the stage (with a folder, once checkpoint_every_s has passed)
                rec._checkpoint_in_stage(work)
            yield from work.hand_over(take_snapshot(rec, stage, it, work.global_iteration, work.terms, work.t0, False, val,
                                                    work.train_error))
            if stalled:
                work.record.stopped_at = it
                break
    work.validation_error = end_on_best(rec, stage, work.mask, work.best, work.done, work.record)
    return True


def capture_branch(rec: Run) -> dict[str, Any]:
    """A full copy of what training changes (volume, calibration and its optimiser, batch order), to start
    several candidates from one state."""
    return {**rec._capture(), "cal_opt": copy.deepcopy(rec.calibration.optimiser.state_dict()),
            "batches": copy.deepcopy(rec.batches.state_dict())}


def restore_branch(rec: Run, state: dict[str, Any]) -> None:
    """Return to a :func:`capture_branch` (copies again, so the state can be restored more than once)."""
    rec._restore(state, keep_bookkeeping=True)
    rec.calibration.optimiser.load_state_dict(copy.deepcopy(state["cal_opt"]))
    rec.batches.load_state_dict(copy.deepcopy(state["batches"]))
