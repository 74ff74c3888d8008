"""The pupil chosen before the stages, from the sources' own light (a pilot at Δn = 0).

The paired test of the pupil (its NA and edge; :mod:`napari_fdt.recon.choices.parts_search`) is made at the finest stage's end.
A part kept there makes every stage run again, since the coarse stages must model it: the default then took 1.6–1.9×
a plain pass on a scene with a hard pupil (docs/decisions/one-pass-default-vs-plain.md). The pupil shapes the images
of the sources themselves, which are most of each image's light, so it can be seen before any volume exists. With
Δn = 0 (the sample's light left unexplained, the same on both sides of the test), the positions, the depth offset and
the gains of the images the test reads (the pupil fit's training images and the held-out ones) are fitted through the
finest stage's model for :data:`~napari_fdt.recon.loop.model_parts.PILOT_ITERATIONS` steps; then the pupil is fitted and
tested as at the finest stage's end, on the held-out images. Kept here, it is on from the first stage (coarse stages
multi-slice, as a rerun would run them) and no stage runs twice for it; not kept, it is tried again at the finest
stage's end, as before. Everything the pilot trained is set back; a kept pupil starts from its fitted values.

Measured (docs/decisions/one-pass-default-vs-plain.md, last section): cells_pupil (a hard pupil its files do not state)
keeps the pupil (held-out error −2.5 % and −3.2 %, z 3.9 and 5.1), and its default run takes 1.15–1.17× a plain pass
with the pupil given; the sample does not (z −0.6), and its run is unchanged.
"""
from __future__ import annotations

import contextlib
import copy
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable, Generator, Iterator

import numpy as np
import torch

from napari_fdt.recon.calibration.calibration import PUPIL_PARAMETERS
from napari_fdt.recon.choices.parts_search import exit_cache, fit_images, fit_pupil_parts, pupil_values
from napari_fdt.recon.choices.parts_switch import parts_chosen_by, set_parts
from napari_fdt.recon.loop.model_parts import PILOT_BATCH, PILOT_ITERATIONS, PartsChoice, decide, pupil_pilot_wanted
from napari_fdt.recon.loop.phases import PUPIL_PILOT
from napari_fdt.recon.loop.run_validation import validation
from napari_fdt.recon.loop.snapshot import Snapshot, take_snapshot
from napari_fdt.recon.problem.losses import BatchShare, total_loss

if TYPE_CHECKING:
    from napari_fdt.recon.loop.interface import Run
    from napari_fdt.recon.loop.stage_loop import StageWork

__all__ = ["SNAPSHOT_EVERY", "PILOT_PARTS", "PilotOutcome", "pilot_due", "choose_pupil_parts_first", "start_with_parts"]

#: Pilot steps between its snapshots (the progress bar's and the widget's updates).
SNAPSHOT_EVERY = 10
#: The parts the pilot tests. The aberrations are not among them: on the tests' scene with 1.2 rad of spherical
#: aberration the pilot missed them (z 0.8) where the finest stage's end finds them, so their test there stays the only one.
PILOT_PARTS = ("pupil",)


@dataclass
class PilotOutcome:
    """What the pilot found: ``kept`` parts, their ``fitted`` values (calibration tensors, :data:`PUPIL_PARAMETERS`),
    the ``trials`` (as :class:`~napari_fdt.recon.loop.model_parts.PartsChoice`'s, each with ``"pass": 0``), the held-out
    error the parts were compared with, and the pilot's seconds."""

    kept: list[str]
    fitted: dict[str, torch.Tensor]
    trials: list[dict[str, Any]] = field(default_factory=list)
    reference_error: float | None = None
    reference_image_errors: list[float] = field(default_factory=list)
    seconds: float = 0.0


def pilot_due(rec: Run) -> bool:
    """A pilot runs where ``parts_pilot`` is on, the pupil is ``"auto"``, nothing is chosen yet (once a run) and at least
    two images are held out (the test's noise estimate). In a distributed run every rank runs it, each on its own images
    (their gradients summed, their errors added: :func:`~napari_fdt.recon.loop.run_validation.image_errors`)."""
    return (rec.parts_choice is None and rec.early_trials is None
            and pupil_pilot_wanted(rec.config, len(rec.validation_indices), "pupil" in rec._auto_parts))


@contextlib.contextmanager
def _no_sample(rec: Run, shape: tuple[int, ...]) -> Iterator[torch.Tensor]:
    """Δn = 0 on the grid ``shape`` for everything that reads the volume (validation, the pupil fits' exit fields)."""
    zero = torch.zeros(shape, device=rec.device, dtype=rec.volume.x.dtype)
    volume = rec.volume
    volume.delta_n = lambda: zero  # an instance attribute over the method, removed below
    try:
        yield zero
    finally:
        del volume.delta_n


def choose_pupil_parts_first(rec: Run, work: StageWork,
                             should_stop: Callable[[], bool] | None) -> Generator[Snapshot, None, PilotOutcome | None]:
    """Run the pilot and the fitted parts' tests (see the module) at the start of the first stage (``work``); the run's
    state is set back. Yields a snapshot every :data:`SNAPSHOT_EVERY` steps (phase ``"pupil_pilot"``: the plan's first
    phase, its volume zero). Returns the outcome, None when stopped."""
    t0 = time.perf_counter()
    cal = rec.calibration
    # what the pilot trains, to set back (the volume and the batch order it does not touch: the stage's optimiser holds
    # the volume's tensor, which must stay the same object)
    start_values, start_opt = cal.copy_values(), copy.deepcopy(cal.optimiser.state_dict())
    last = len(rec.config.stages) - 1
    stage = rec._build_stage(last)
    mask = rec._loss_mask(stage)
    cal.set_trainable(last)
    held = torch.as_tensor(rec.validation_indices, device=rec.device)
    fit = fit_images(rec)
    rng = np.random.default_rng(rec.config.seed)
    data_range = float(stage.images.max())
    outcome = PilotOutcome([], {})
    stage_phase = rec._phase_index
    rec._phase_index = rec.plan.index(PUPIL_PILOT, last)
    try:
        with _no_sample(rec, (rec.acquisition.optics.n_slices, *rec.full_shape)) as zero:
            for step in range(1, PILOT_ITERATIONS + 1):
                if rec._stop_requested(should_stop):
                    return None
                f = fit[torch.as_tensor(rng.permutation(len(fit))[:PILOT_BATCH], device=rec.device)]
                h = held[torch.as_tensor(rng.permutation(len(held))[:PILOT_BATCH], device=rec.device)]
                idx = torch.cat([f, h])
                share = None
                if rec.group is not None:  # as a training step: each rank its own images, normalised by the whole batch
                    share = BatchShare.of_batch(None if mask is None else mask[idx], (len(idx), *stage.images.shape[1:]),
                                                regularisers=rec.group.is_writer)
                    f, h = rec.group.local(f), rec.group.local(h)
                    idx = torch.cat([f, h])
                pred = torch.cat([rec._predict_normalised(stage, zero, f), rec._predict_normalised(stage, zero, h, held_out=True)])
                loss, terms = total_loss(pred, stage.images[idx], zero, rec.loss_weights, 0.0,
                                         mask=None if mask is None else mask[idx], data_range=data_range, share=share)
                cal.optimiser.zero_grad(set_to_none=True)
                if loss.requires_grad:  # (a rank with none of the batch: no graph, zeros in the sum below)
                    loss.backward()
                if rec.group is not None:
                    rec.group.reduce_gradients(list(cal.shared_parameters()), cal.per_source_parameters())
                cal.optimiser.step()
                if step % SNAPSHOT_EVERY == 0:
                    yield from work.hand_over(take_snapshot(rec, stage, step, work.base_iteration, terms, work.t0, False,
                                                            in_history=False))
            ref_err, ref_each = validation(rec, stage, mask, per_image=True)
            outcome.reference_error, outcome.reference_image_errors = ref_err, list(ref_each)
            for part in [p for p in PILOT_PARTS if p in rec._auto_parts]:
                t1 = time.perf_counter()
                before = cal.copy_values()
                set_parts(rec, {**rec.parts, part: True})
                variant = rec._build_stage(last)
                if not fit_pupil_parts(rec, variant, exit_cache(rec, variant), [part], should_stop):
                    return None
                err, each = validation(rec, variant, rec._loss_mask(variant), per_image=True)
                verdict = decide(np.asarray(ref_each), each)
                outcome.trials.append({"part": part, "validation_error": err, "image_errors": each, **verdict,
                                       "fitted": pupil_values(rec, [part]), "seconds": time.perf_counter() - t1, "pass": 0,
                                       "reference_error": ref_err})
                if verdict["on"]:
                    outcome.kept.append(part)
                    ref_each = each
                else:
                    set_parts(rec, {**rec.parts, part: False})
                    cal.restore_values(before)
            outcome.fitted = cal.copy_values(PUPIL_PARAMETERS)
    finally:
        set_parts(rec, {**rec.parts, **{p: False for p in PILOT_PARTS if p in rec._auto_parts}})
        cal.restore_values(start_values)
        cal.optimiser.load_state_dict(start_opt)
        cal.set_trainable(0)
        rec._phase_index = stage_phase
    outcome.seconds = time.perf_counter() - t0
    for t in outcome.trials:  # the whole pilot's time (its calibration steps and the tests) on its trials, for RI.json
        t["pilot_s"] = outcome.seconds
    return outcome


def start_with_parts(rec: Run, outcome: PilotOutcome) -> None:
    """The pilot kept ``outcome.kept``: a choice made before the stages (``rerun`` ``"before"``). The kept parts are on
    from the first stage, from their fitted values, with multi-slice coarse stages (under ``coarse_model`` ``"auto"``,
    as a rerun with them has); the other auto parts are chosen at the finest stage's end; the plan's phases are priced
    again for that model."""
    parts = {**rec.parts, **{p: True for p in outcome.kept}}
    fitted = {k: v for t in outcome.trials if t["part"] in outcome.kept for k, v in t["fitted"].items()}
    choice = PartsChoice(parts, parts_chosen_by(rec), stage=-1, reference_error=outcome.reference_error,
                         reference_image_errors=outcome.reference_image_errors, trials=list(outcome.trials), fitted=fitted,
                         seconds=outcome.seconds, rerun="before", pending=[p for p in rec._auto_parts if not parts[p]])
    rec.apply_parts_choice(choice)
    rec._restart()
    rec.calibration.restore_values(outcome.fitted)  # the kept parts start from their fitted values
    kept = tuple(outcome.kept)
    phases = []
    for p in rec.plan.phases:
        if p.pass_name == PUPIL_PILOT:  # (done)
            phases.append(p)
            continue
        q = rec._stage_phase(p.stage, p.pass_name, kept)
        phases.append(p.priced_as(q))
    rec._revise_plan(replace(rec.plan, phases=tuple(phases)))
