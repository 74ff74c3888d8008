"""A kept part earns its place at the end: the backward step of the ``"auto"`` model parts (issue 49).

The choice (:mod:`napari_fdt.recon.choices.parts_search`, :mod:`napari_fdt.recon.choices.parts_coarse_end`) admits parts one at a
time, each through a volume trained without it, and never looks at a kept part again: a part kept early (the
aberrations at the ×2 stage's end, a spectral model) may have absorbed what a part kept later (sub-slices) explains.
Once the final set is trained (the finest stage's end, nothing left to choose), each kept ``"auto"`` part is tested
for removal:

1. The held-out images are predicted through the final state with that part off, the others on (a fitted part at its
   nominal values: NA and edge as stated, no Zernike phase), and paired against the final state's own predictions.
2. The part earns its place when its removal makes them worse by more than noise: the admission's rule
   (:func:`~napari_fdt.recon.loop.model_parts.decide`: the mean paired difference above Student's t quantile times its
   standard error, and above :data:`~napari_fdt.recon.loop.model_parts.MIN_IMPROVEMENT` of the error). The same rule in
   the other direction: a part is dropped only where its removal is *not* worse by more than noise, so no part is kept
   or dropped on a difference below it that the admission would not have accepted either.
3. Parts that do not earn their place are dropped together, and the finest stage runs again from its start without
   them (the plan appends that phase). The stages before keep what they were (re-run only what must be). At that
   stage's end the rerun's held-out errors are paired with the state before the drop; where the rerun is worse by more
   than noise, the run returns to that state with the parts on (:func:`keep_the_better`).

Held-out images only (not ``parts_test_images``' training images): the final volume was trained on the training
images with the part on, so they favour it.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from napari_fdt.recon.choices.parts_switch import set_parts
from napari_fdt.recon.loop.model_parts import FITTED_PARTS, decide, parts_stage
from napari_fdt.recon.loop.run_validation import validation

if TYPE_CHECKING:
    import torch

    from napari_fdt.recon.loop.interface import Run
    from napari_fdt.recon.loop.stage_loop import StageWork
    from napari_fdt.recon.problem.stages import Stage

__all__ = ["kept_auto_parts", "marginal_effects", "keep_the_better", "backward_due", "drop_parts", "keep_or_return"]

#: Parts whose removal needs no new stage model (the spectral model's wavelengths and the pupil's values are read at
#: prediction time); the others change the stage's model (screens, grid, obliquity).
_NO_REBUILD = ("spectral",) + FITTED_PARTS


def kept_auto_parts(rec: Run) -> list[str]:
    """The parts on that the data chose (``chosen_by`` ``"validation"``), in the choice's order."""
    choice = rec.parts_choice
    if choice is None:
        return []
    return [p for p, on in rec.parts.items() if on and choice.chosen_by.get(p) == "validation"]


def _held_out(rec: Run, stage: Stage, mask: torch.Tensor | None) -> tuple[float, list[float]]:
    out = validation(rec, stage, mask, per_image=True)
    assert out is not None  # (only called with a validation split)
    return out[0], list(out[1])


def marginal_effects(rec: Run, stage: Stage, mask: torch.Tensor | None) -> dict[str, Any]:
    """Each kept ``"auto"`` part's effect on the held-out images in the final state: RI.json's
    ``model_parts.chosen.backward`` (without the rerun's fields). ``reference_error``: the final state's held-out error;
    ``effects``: per part the held-out error without it, ``improvement`` (mean paired error without − with; positive:
    the part helps), its ``standard_error``, ``threshold`` and ``earns`` (:func:`decide`'s verdict); ``dropped``: the
    parts that do not earn their place. The parts and the calibration are as they were on return."""
    t0 = time.perf_counter()
    parts = dict(rec.parts)
    ref_err, ref_each = _held_out(rec, stage, mask)
    effects = []
    try:
        for part in kept_auto_parts(rec):
            set_parts(rec, {**parts, part: False})
            variant = stage if part in _NO_REBUILD else rec._build_stage(stage.index)
            err, each = _held_out(rec, variant, mask if variant is stage else rec._loss_mask(variant))
            verdict = decide(each, ref_each)  # the part as the candidate against the model without it
            effects.append({"part": part, "validation_error_without": err, "image_errors_without": each,
                            "improvement": verdict["improvement"], "standard_error": verdict["standard_error"],
                            "threshold": verdict.get("threshold"), "earns": verdict["on"]})
    finally:
        set_parts(rec, parts)
    return {"reference_error": ref_err, "reference_image_errors": ref_each, "effects": effects,
            "dropped": [e["part"] for e in effects if not e["earns"]], "seconds": time.perf_counter() - t0}


def keep_the_better(before_each: list[float], after_each: list[float], after_error: float) -> dict[str, Any]:
    """After the finest stage ran again without the dropped parts: whether to keep that rerun (``keep_rerun``), from the
    held-out errors of the state before the drop (``before_each``) and of the rerun (``after_each``, the same images).
    The rerun is kept unless it is worse by more than noise (the admission's test, the state before as the candidate)."""
    verdict = decide(after_each, before_each)
    return {"improvement_before_drop": verdict["improvement"], "standard_error": verdict["standard_error"],
            "keep_rerun": not verdict["on"], "validation_error_rerun": after_error}


def backward_due(rec: Run, stage_index: int) -> bool:
    """Whether the backward step may run at the end of stage ``stage_index``: ``parts_backward`` on, a validation split,
    ``"auto"`` parts in the run, the finest stage (:func:`~napari_fdt.recon.loop.model_parts.parts_stage`), and no backward
    step made yet."""
    choice = rec.parts_choice
    return (bool(rec.config.parts_backward) and len(rec.validation_indices) >= 2 and stage_index == parts_stage(rec.config)
            and (bool(rec._auto_parts) or bool(kept_auto_parts(rec))) and (choice is None or choice.backward is None))


def drop_parts(rec: Run, result: dict[str, Any]) -> tuple[dict[str, Any], list[float], dict[str, bool]]:
    """Switch off ``result["dropped"]`` (:func:`marginal_effects`' outcome) and return what the rerun's end compares
    with: (a copy of the state before the drop, its held-out errors per image, the parts as they were)."""
    from napari_fdt.recon.loop.stage_loop import capture_branch

    before = (capture_branch(rec), list(result["reference_image_errors"]), dict(rec.parts))
    set_parts(rec, {**rec.parts, **{p: False for p in result["dropped"]}})
    rec.parts_choice.parts = dict(rec.parts)
    return before


def keep_or_return(rec: Run, work: StageWork, before: tuple[dict[str, Any], list[float], dict[str, bool]]) -> bool:
    """At the end of the finest stage run again without the dropped parts: keep it (True) unless its held-out images
    are worse than the state before the drop by more than noise; then return to that state, the parts on again
    (False: the caller rebuilds the stage's model). The outcome goes to ``backward["rerun"]``."""
    from napari_fdt.recon.loop.stage_loop import restore_branch

    state, before_each, parts = before
    err, after_each = _held_out(rec, work.stage, work.mask)
    outcome = keep_the_better(before_each, after_each, err)
    rec.parts_choice.backward["rerun"] = outcome
    if outcome["keep_rerun"]:
        return True
    set_parts(rec, parts)
    rec.parts_choice.parts = dict(rec.parts)
    restore_branch(rec, state)
    return False
