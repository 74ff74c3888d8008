"""The trial of a part that changes what the volume must be (sub-slices, the 2x field grid) by a short branch of training
(issue 49: physics before phenomenology).

The choice's usual trial (:func:`~napari_fdt.recon.choices.parts_search.choose_parts`) predicts the test images with the
part on through the volume trained without it. For the parts that make the model more exact that trial is blind: a volume
trained through thin screens has adapted to them, and the more exact model through it predicts no better. On beads made
with 4 screens per slice (beads_high, seed 0) sub-slices through that volume changed the held-out error by
+0.1 % ± 0.4 % (rejected), while the run trained with them ended 13 % lower on the held-out images and at Δn error 0.367
against 0.415; the spectral model, whose blur absorbed the thin screens' error, was kept in their place
(docs/decisions/parts-backward.md).

The branch trial trains from the stage's end twice for
:func:`~napari_fdt.recon.loop.model_parts.branch_iterations` iterations, once with the part off and once with it on, from
the same state (volume, calibration and its optimiser, batch order) and with the same short step schedule (from
:data:`BRANCH_STEP_SCALE` of ``lr_ri`` down to ``lr_ri_final_ratio`` of it), and pairs the held-out images' errors at the
two ends with the admission's rule (:func:`~napari_fdt.recon.loop.model_parts.decide`). Held-out images only: the
training images were trained on in both arms. The state is returned to the stage's end afterwards, whatever the verdict.
A part kept so makes every stage run again with it (coarse stages multi-slice: the thin model's volume differs from the
coarse stages on), and the parts not yet tried wait for that pass (:func:`defers_the_rest`).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, Callable

from napari_fdt.recon.choices.parts_switch import set_parts
from napari_fdt.recon.loop.model_parts import FINEST_ONLY_PARTS, branch_iterations, decide
from napari_fdt.recon.loop.run_validation import validation
from napari_fdt.recon.loop.stage_loop import capture_branch, new_optimiser, restore_branch
from napari_fdt.recon.settings.schedule import final_step_scale

if TYPE_CHECKING:
    import torch

    from napari_fdt.recon.loop.interface import Run
    from napari_fdt.recon.problem.stages import Stage

__all__ = ["BRANCH_STEP_SCALE", "branch_due", "defers_the_rest", "branch_trial"]

#: The branch's first RI step as a share of ``lr_ri``: the stage's end has a small step, and a branch restarted at the
#: full step first makes the held-out images worse (beads, 16 iterations from ``lr_ri``: +11 % in the arm without the
#: part), which hides the part's effect in the restart's.
BRANCH_STEP_SCALE = 0.3


def branch_due(rec: Run, part: str) -> bool:
    """Whether ``part``, rejected by the trial through the volume, gets a branch trial: ``parts_branch`` on, a part of the
    finest stage's model (:data:`FINEST_ONLY_PARTS`) and at least two held-out images (the paired test's noise). Not
    gated on how much worse the part looked through the volume: on beads made with four screens per slice it looked
    worse by 0.1-1.2 % (z −0.4 to −3.9, the latter through multi-slice coarse stages), on cells made with one by
    3.6-6.5 % (z −8 to −16): a gate there would decide on a margin that no noise rule sets."""
    return bool(rec.config.parts_branch) and part in FINEST_ONLY_PARTS and len(rec.validation_indices) >= 2


def defers_the_rest(rec: Run) -> bool:
    """Whether a part kept by a branch trial sends the parts not yet tried to the finest stage's end of the pass that runs
    every stage again with it (the first choice, with ``parts_rerun`` ``"stages"``: the parts not kept are tried again
    there): they are then tried through a volume trained with the more exact model, not through one that a part able to
    absorb any residual (the spectral model, the aberrations) would mend in its place."""
    return rec.parts_choice is None and rec.config.parts_rerun == "stages"


def _arm(rec: Run, stage: Stage, mask: torch.Tensor | None, iterations: int,
         should_stop: Callable[[], bool] | None) -> list[float] | None:
    """Train ``iterations`` steps from the current state through ``stage``; the held-out images' errors at the end (None
    when stopped)."""
    cfg = rec.config
    opt = new_optimiser(rec)
    batch, data_range = cfg.stage_batch(stage.index), float(stage.images.max())
    for it in range(1, iterations + 1):
        if rec._stop_requested(should_stop):
            return None
        for group in opt.param_groups:
            group["lr"] = BRANCH_STEP_SCALE * cfg.lr_ri * final_step_scale(it, iterations, cfg.lr_ri_final_ratio)
        rec._step(stage, mask, opt, batch, data_range, 1.0)
    out = validation(rec, stage, mask, per_image=True)
    assert out is not None  # (only called with a validation split)
    return list(out[1])


def branch_trial(rec: Run, stage: Stage, mask: torch.Tensor | None, part: str,
                 should_stop: Callable[[], bool] | None) -> dict[str, Any] | None:
    """The branch trial of ``part`` (a part of :data:`~napari_fdt.recon.loop.model_parts.FINEST_ONLY_PARTS`) at the end of
    ``stage``, the finest: the trial's record (``test`` ``"branch"``, its ``iterations``, the held-out errors of each arm,
    :func:`decide`'s verdict with the arm without the part as the reference). The run's state and parts are as they
    were on return; None when stopped meanwhile."""
    t0 = time.perf_counter()
    start, parts = capture_branch(rec), dict(rec.parts)
    iterations = branch_iterations(stage.iterations)
    try:
        without = _arm(rec, stage, mask, iterations, should_stop)
        if without is None:
            return None
        restore_branch(rec, start)
        set_parts(rec, {**parts, part: True})
        variant = rec._build_stage(stage.index)
        with_part = _arm(rec, variant, rec._loss_mask(variant), iterations, should_stop)
        if with_part is None:
            return None
    finally:
        restore_branch(rec, start)
        set_parts(rec, parts)
    verdict = decide(without, with_part)
    return {"part": part, "test": "branch", "iterations": iterations, "validation_error": sum(with_part) / len(with_part),
            "validation_error_without": sum(without) / len(without), "image_errors": with_part,
            "image_errors_without": without, **verdict, "seconds": time.perf_counter() - t0}
