"""The pupil parts tested at the last coarse stage's end, before the finest stage runs.

A part kept at the finest stage's end makes every stage run again with it (the coarse stages must model it:
docs/decisions/model-parts.md), so a run that needs the aberrations paid its finest stage twice. The aberrations are
not seen at Δn = 0 (the pupil's pilot, :mod:`napari_fdt.recon.choices.parts_pilot`), but they are seen through the volume of
the last coarse stage: at its end the volume is carried (as a copy) to the finest stage's grid and the aberrations,
where still ``"auto"``, are fitted and tested there through the finest stage's model, as at the finest stage's end
(:func:`~napari_fdt.recon.choices.parts_search.try_fitted_parts`), with a larger floor on the improvement
(:data:`~napari_fdt.recon.loop.model_parts.COARSE_END_MIN_IMPROVEMENT`: a fit through a coarse volume also absorbs what
the volume still lacks). Kept, every stage runs again from the first with them (``rerun`` ``"stages"``, as a keep at
the finest stage's end does) and the first pass's finest stage never runs. In that second pass (and in any pass that
runs every stage again with kept parts) the pupil parts still to choose are tested at the same stage's end, through a
volume now trained with the kept parts on the multi-slice model; kept there, they are on from the finest stage's
start. Whatever is not kept is tried again at the finest stage's end.

Measured (docs/decisions/model-parts.md, "The aberrations at the last coarse stage's end"): the aberrations kept at
the ×2 stage's end on beads_real and letters_real (4.5-5.2 % of the test images' error, z 9.2-10.1, seeds 0 and 1);
on the scenes without aberrations at most 1.06 % (the sample). The pupil shows nowhere in the first pass (at most
0.53 %, on letters_real), but in the second pass it was kept on beads_real and letters_real, whose pupil is hard:
their default runs took 0.76-0.81x the time and beads_real's Δn error fell from 0.385 to 0.210 (seed 1), where the
finest stage's end had never kept that pupil.
"""
from __future__ import annotations

import copy
import time
from typing import TYPE_CHECKING, Callable

from napari_fdt.recon.choices.parts_search import choice_errors, pupil_values, try_fitted_parts
from napari_fdt.recon.choices.parts_switch import parts_chosen_by, restart_with_parts, set_parts
from napari_fdt.recon.loop.model_parts import (
    COARSE_END_MIN_IMPROVEMENT,
    FITTED_PARTS,
    EarlyTrials,
    PartsChoice,
    coarse_end_test_planned,
    coarse_test_stage,
    next_pass,
    parts_stage,
)
from napari_fdt.recon.loop.phases import RERUN, RUN
from napari_fdt.recon.loop.snapshot import rerun_parts

if TYPE_CHECKING:
    from napari_fdt.recon.loop.interface import Run
    from napari_fdt.recon.loop.stage_loop import StageWork

__all__ = ["COARSE_END_PARTS", "coarse_end_parts", "coarse_end_test_due", "early_test_stage", "choose_fitted_parts_at_coarse_end"]

#: The parts tested at the last coarse stage's end.
COARSE_END_PARTS = ("aberrations",)


def coarse_end_parts(rec: Run) -> list[str]:
    """The parts the test at the last coarse stage's end tries: in the first pass (nothing chosen yet) the ``"auto"``
    aberrations; in a pass that runs every stage again with parts kept (``rerun`` ``"stages"``: its coarse stages
    multi-slice with them), the parts with parameters still to choose; else none."""
    choice = rec.parts_choice
    if choice is None:
        return [p for p in COARSE_END_PARTS if p in rec._auto_parts]
    if choice.rerun == "stages":
        return [p for p in FITTED_PARTS if p in rec._choose_again]
    return []


def early_test_stage(rec: Run) -> int | None:
    """The stage at whose end ``rec``'s first pass will test the aberrations, for its plan (None: no such test ahead)."""
    stage = coarse_test_stage(rec.config)
    planned = coarse_end_test_planned(rec.config, len(rec.validation_indices), "aberrations" in rec._auto_parts)
    return stage if planned and rec.parts_choice is None and rec.completed_stages <= stage else None


def coarse_end_test_due(rec: Run, work: StageWork) -> bool:
    """Whether the test runs at the end of ``work``'s stage: :func:`coarse_end_test_planned` with a part to try
    (:func:`coarse_end_parts`), and this the stage of :func:`coarse_test_stage`."""
    return (coarse_end_test_planned(rec.config, len(rec.validation_indices), bool(coarse_end_parts(rec)))
            and work.stage.index == coarse_test_stage(rec.config))


def choose_fitted_parts_at_coarse_end(rec: Run, work: StageWork, should_stop: Callable[[], bool] | None) -> bool | None:
    """Test :func:`coarse_end_parts` at the end of ``work``'s stage (see the module). True when the first pass kept a
    part (the run is then set back to its first stage, the kept parts on from their fitted values, the plan without the
    first pass's finest stage and with every stage again); False otherwise (the run goes on: with nothing kept, its
    state as it was; a part kept in a pass run again is on from the finest stage's start). The trials are kept for
    RI.json. None when stopped."""
    t0 = time.perf_counter()
    cal = rec.calibration
    start_values, provisional = cal.copy_values(), dict(rec.parts)
    volume, factor = rec.volume, rec.volume_factor
    parts = coarse_end_parts(rec)
    rec.volume = copy.deepcopy(volume)  # the run's volume (its tensor is the stage optimiser's) stays on its grid
    try:
        finest = rec._build_stage(parts_stage(rec.config))
        rec._carry_volume_to(finest)
        mask = rec._loss_mask(finest)
        ref_err, ref_each = choice_errors(rec, finest, mask)
        tested = try_fitted_parts(rec, finest, mask, list(ref_each), parts, should_stop, COARSE_END_MIN_IMPROVEMENT)
    finally:
        rec.volume, rec.volume_factor = volume, factor
    if tested is None:
        cal.restore_values(start_values)
        set_parts(rec, provisional)
        return None
    at, kept, seconds = work.stage.index, [p for p in parts if rec.parts[p]], time.perf_counter() - t0
    work.record.choice_s += seconds  # not the stage's own iterations
    if rec.parts_choice is not None:  # a pass run again: what it keeps is on from the finest stage's start
        _keep_for_the_finest_stage(rec, tested[0], kept, at, ref_err, seconds)
        return False
    trials = [{**t, "pass": 1, "at_stage": at, "reference_error": ref_err} for t in tested[0]]
    early = rec.early_trials
    if early is not None:  # the pupil's pilot kept nothing: its trials first
        trials, seconds = early.trials + trials, seconds + early.seconds
    if not kept:  # as it was; the finest stage's end tries them again (its choice lists these trials first)
        rec.early_trials = EarlyTrials(trials, seconds)
        return False
    rec.apply_parts_choice(PartsChoice(dict(rec.parts), parts_chosen_by(rec), stage=at, iteration=work.done, reference_error=ref_err,
                                       reference_image_errors=list(ref_each), trials=trials,
                                       fitted=pupil_values(rec, kept), seconds=seconds))
    finest_run = rec.plan.index(RUN, parts_stage(rec.config))
    rec._revise_plan(rec.plan.without(finest_run))  # the first pass's finest stage never runs
    restart_with_parts(rec)  # every stage again from the first with the kept parts (the plan appends them)
    return True


def _keep_for_the_finest_stage(rec: Run, trials: list[dict], kept: list[str], at: int, ref_err: float,
                               seconds: float) -> None:
    """In a pass run again: the trials added to the choice (this pass's number, ``after`` "stages"); the kept parts
    (on, their fitted values in the calibration) leave the parts the finest stage's end chooses, and the plan prices
    that stage with them."""
    choice = rec.parts_choice
    n = next_pass(choice.trials)
    choice.trials = choice.trials + [{**t, "pass": n, "after": "stages", "at_stage": at, "reference_error": ref_err}
                                     for t in trials]
    choice.seconds += seconds
    if not kept:
        return
    choice.parts = dict(rec.parts)
    choice.fitted = pupil_values(rec, [p for p in FITTED_PARTS if rec.parts[p]])
    rec._choose_again = [p for p in rec._choose_again if p not in kept]
    rec._auto_parts = [p for p in rec._auto_parts if p not in kept]
    choice.pending = list(rec._choose_again)
    finest = parts_stage(rec.config)
    index = rec.plan.index(RERUN, finest)
    q = rec._stage_phase(finest, RERUN, rerun_parts(rec))
    rec._revise_plan(rec.plan.with_phase(index, rec.plan.phases[index].priced_as(q, label=True)))
