"""The choices a run makes from its data, as phases plugged into the stage loop (:class:`~napari_fdt.recon.loop.stage_loop.Choice`).

:class:`ChooseTVWeights`
    At the selection stage's start (``"auto"`` TV weights): the trials of :mod:`napari_fdt.recon.choices.tv_search`; the stage
    goes on from the winner, or every stage runs again with it where it changes what the stages before did.
:class:`ChooseModelParts`
    Before the first stage, the pupil parts from a pilot at Δn = 0 (:mod:`napari_fdt.recon.choices.parts_pilot`: a part kept
    there is on from the first stage). At the last coarse stage's end, the aberrations through its volume
    (:mod:`napari_fdt.recon.choices.parts_coarse_end`: kept there, every stage runs again before the finest stage has run once;
    in that second pass the pupil parts still to choose are tested there too, a part kept then on from the finest
    stage's start). At the end of the first multi-slice stage (``"auto"`` model parts): the paired test of
    :mod:`napari_fdt.recon.choices.parts_search`; where a part is kept, every stage runs again with it (``parts_rerun``
    ``"stages"``) or the stage again from its start (``"finest"``). Where the kept parts change only the finest stage's
    model (:data:`~napari_fdt.recon.loop.model_parts.FINEST_ONLY_PARTS`) and the trial through the volume kept them (not
    a branch of training, :mod:`napari_fdt.recon.choices.parts_branch`), the finest stage runs again from its start with
    them and, under ``"stages"``, the parts not kept are tried again at its end (a part kept then makes every stage run
    again, with all the kept parts).
:class:`ConfirmModelParts`
    At the finest stage's end, once nothing is left to choose: each kept part tested for removal through the final
    state (:mod:`napari_fdt.recon.choices.parts_backward`); one that no longer helps is dropped and the stage runs again
    without it.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import TYPE_CHECKING, Callable, Generator

from napari_fdt.recon.assess.validation import BestIterate
from napari_fdt.recon.calibration.calibration import PUPIL_PARAMETERS
from napari_fdt.recon.choices.parts_backward import backward_due, drop_parts, keep_or_return, kept_auto_parts, marginal_effects
from napari_fdt.recon.choices.parts_coarse_end import choose_fitted_parts_at_coarse_end, coarse_end_test_due
from napari_fdt.recon.choices.parts_pilot import choose_pupil_parts_first, pilot_due, start_with_parts
from napari_fdt.recon.choices.parts_search import choose_parts
from napari_fdt.recon.choices.parts_switch import finest_again_with_parts, parts_chosen_by, restart_with_parts, tests_again_s
from napari_fdt.recon.choices.tv_search import choose_tv
from napari_fdt.recon.loop.model_parts import FINEST_ONLY_PARTS, EarlyTrials, PartsChoice, parts_stage
from napari_fdt.recon.loop.regularisation import selection_stages, tv_is_auto
from napari_fdt.recon.loop.snapshot import Snapshot
from napari_fdt.recon.loop.stage_loop import StageWork, Verdict, capture_branch, new_optimiser, restore_branch

if TYPE_CHECKING:
    from napari_fdt.recon.loop.interface import Run
    from napari_fdt.recon.loop.plan import Phase

__all__ = ["ChooseTVWeights", "ChooseModelParts", "ConfirmModelParts", "default_choices"]


class ChooseTVWeights:
    """The ``"auto"`` TV weights, chosen at the start of the selection stage (:func:`~napari_fdt.recon.choices.tv_search.choose_tv`)."""

    def at_start(self, rec: Run, work: StageWork, again: int,
                 should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, Verdict]:
        cfg = rec.config
        if rec.tv_choice is not None or not tv_is_auto(cfg) or work.stage.index not in selection_stages(cfg):
            return Verdict.GO_ON
        verdict = yield from choose_tv(rec, work, should_stop)
        if verdict is Verdict.FROM_FIRST_STAGE:  # the weight changes what the stages before did: again with it
            rec._restart(keep_last_complete=True)
        elif verdict is Verdict.GO_ON:
            rec._enter_stage_phase(work.stage.index)  # the stage's own phase after the trials'
        return verdict

    def at_end(self, rec: Run, work: StageWork, should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, Verdict]:
        return Verdict.GO_ON
        yield  # (a generator)


class ChooseModelParts:
    """The ``"auto"`` model parts, chosen at the end of the first multi-slice stage
    (:func:`~napari_fdt.recon.choices.parts_search.choose_parts`)."""

    def at_start(self, rec: Run, work: StageWork, again: int,
                 should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, Verdict]:
        cfg = rec.config
        if work.stage.index == 0 and not again and pilot_due(rec):  # the pupil parts first, from the sources' light
            outcome = yield from choose_pupil_parts_first(rec, work, should_stop)
            if outcome is None:
                return Verdict.STOPPED
            work.record.choice_s += outcome.seconds  # not the stage's own iterations
            if outcome.kept:  # on from the first stage: no stage runs twice for them
                start_with_parts(rec, outcome)
                return Verdict.FROM_FIRST_STAGE
            rec.early_trials = EarlyTrials(list(outcome.trials), outcome.seconds)  # listed first by the choice to come
        due = (rec.parts_choice is None or rec._choose_again) and work.stage.index == parts_stage(cfg)
        if again or not due:
            return Verdict.GO_ON
        if work.stage.envelope:  # the parts belong to the multi-slice model: nothing to choose on this run's stages
            rec.apply_parts_choice(PartsChoice(dict(rec.parts), parts_chosen_by(rec, "not chosen: no multi-slice stage")))
        else:  # chosen at the stage's end; the stage may run again from here
            work.choosing["parts_from"] = capture_branch(rec)
        return Verdict.GO_ON
        yield  # (a generator)

    def at_end(self, rec: Run, work: StageWork, should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, Verdict]:
        start = work.choosing.pop("parts_from", None)
        if start is None and coarse_end_test_due(rec, work):  # the pupil parts through the coarse volume
            kept = choose_fitted_parts_at_coarse_end(rec, work, should_stop)
            if kept is None:
                return Verdict.STOPPED
            return Verdict.FROM_FIRST_STAGE if kept else Verdict.GO_ON
        if start is None:
            return Verdict.GO_ON
        t0 = time.perf_counter()
        chosen = choose_parts(rec, work.stage, work.mask, should_stop)
        if chosen is None:
            return Verdict.STOPPED
        work.record.choice_s += time.perf_counter() - t0  # not the stage's own iterations
        rec.parts_choice.iteration = work.done
        if not any(rec.parts[p] for p in rec._auto_parts):
            rec._revise_plan(rec.plan.choices_made())  # nothing kept: the run adds nothing more (its plan's top goes)
            return Verdict.GO_ON
        kept = tuple(p for p in rec._auto_parts if rec.parts[p])
        # the stages before would run as they did; not where a branch found the part (its volume differs from the thin
        # model's from the coarse stages on: beads_high seed 1, Δn error 0.455 with the finest stage again, 0.313 with
        # multi-slice coarse stages; docs/decisions/parts-backward.md)
        by_branch = any(t.get("test") == "branch" and t["on"] for t in rec.parts_choice.trials)
        finest_only = set(kept) <= set(FINEST_ONLY_PARTS) and not by_branch
        if rec.config.parts_rerun == "stages" and rec.parts_choice.rerun != "stages" and not finest_only:
            restart_with_parts(rec)  # every stage again from the first with the kept parts (the plan appends them)
            return Verdict.FROM_FIRST_STAGE
        not_kept = [p for p in rec._auto_parts if p not in kept]
        choose_again = finest_only and bool(not_kept) and rec.parts_choice.rerun is None and rec.config.parts_rerun == "stages"
        if choose_again:  # the parts not kept are tried again at the end, through a volume trained with the kept ones
            finest_again_with_parts(rec)
            work.choosing["parts_from"] = start
        # the stage again from its start, with the kept parts on from their fitted values (a phase of its own, priced
        # with them)
        tests = tests_again_s(rec, tuple(kept_auto_parts(rec))) if choose_again else None
        rec._revise_plan(rec.plan.with_rerun([_stage_again_phase(rec)], choice_to_come=choose_again, tests_s=tests))
        rec._phase_index = len(rec.plan.phases) - 1
        fitted = rec.calibration.copy_values(PUPIL_PARAMETERS)
        restore_branch(rec, start)
        rec.calibration.restore_values(fitted)
        rec.calibration.set_trainable(chosen.index)
        work.stage, work.mask, work.done = chosen, rec._loss_mask(chosen), 0
        work.optimiser, work.data_range = new_optimiser(rec), float(chosen.images.max())
        work.best = BestIterate(tolerance=rec.config.early_stopping_tolerance)
        work.record.stopped_at = None
        return Verdict.STAGE_AGAIN
        yield  # (a generator)


class ConfirmModelParts:
    """The backward step of the ``"auto"`` model parts at the finest stage's end, once nothing is left to choose
    (:mod:`napari_fdt.recon.choices.parts_backward`): a kept part that no longer helps is dropped and the stage runs again
    from its start without it; at that rerun's end the better of the two (by the held-out images) is kept."""

    def at_start(self, rec: Run, work: StageWork, again: int,
                 should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, Verdict]:
        if backward_due(rec, work.stage.index):  # the stage's start, shared with the parts' choice where it took one
            work.choosing["backward_from"] = work.choosing.get("parts_from") or capture_branch(rec)
        return Verdict.GO_ON
        yield  # (a generator)

    def at_end(self, rec: Run, work: StageWork, should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, Verdict]:
        start, before = work.choosing.pop("backward_from", None), work.choosing.pop("backward_before", None)
        if before is not None:  # the stage ran again without the dropped parts: keep that rerun, or go back
            if not keep_or_return(rec, work, before):
                _rebuild(rec, work)
            return Verdict.GO_ON
        if start is None or rec._choose_again or not kept_auto_parts(rec):
            return Verdict.GO_ON
        t0 = time.perf_counter()
        result = marginal_effects(rec, work.stage, work.mask)
        work.record.choice_s += time.perf_counter() - t0
        rec.parts_choice.backward = {**result, "rerun": None}
        if not result["dropped"]:
            return Verdict.GO_ON
        work.choosing["backward_before"] = drop_parts(rec, result)
        rec._revise_plan(replace(rec.plan.with_rerun([_stage_again_phase(rec)]), if_part_dropped_s=None))
        rec._phase_index = len(rec.plan.phases) - 1
        restore_branch(rec, start)
        _rebuild(rec, work)
        work.done, work.optimiser = 0, new_optimiser(rec)
        work.best = BestIterate(tolerance=rec.config.early_stopping_tolerance)
        work.record.stopped_at = None
        return Verdict.STAGE_AGAIN
        yield  # (a generator)


def _stage_again_phase(rec: Run) -> Phase:
    """The current stage again from its start, priced (and labelled) with every part the run keeps now, those kept in
    a pass before included; without the tests at the end of the phase it repeats (they ran: where more are to come,
    :meth:`~napari_fdt.recon.loop.plan.Plan.with_rerun` prices them)."""
    phase = rec.plan.phases[rec._phase_index]
    again = phase.priced_as(rec._stage_phase(phase.stage, phase.pass_name, tuple(kept_auto_parts(rec))), label=True)
    return replace(again, test_s=0.0, test="")


def _rebuild(rec: Run, work: StageWork) -> None:
    """The stage's model for the parts now on."""
    work.stage = rec._build_stage(work.stage.index)
    work.mask, work.data_range = rec._loss_mask(work.stage), float(work.stage.images.max())
    rec.calibration.set_trainable(work.stage.index)


def default_choices() -> tuple[ChooseModelParts, ChooseTVWeights, ConfirmModelParts]:
    """The choices of every run, in the order they are called (the parts' start state is taken before the TV trials
    of a stage that holds both; the backward step after the parts' choice has nothing left to choose)."""
    return ChooseModelParts(), ChooseTVWeights(), ConfirmModelParts()
