"""The validation error during a run: the held-out images predicted through a :class:`~napari_fdt.recon.run.solver.Reconstructor`'s
current state, and the stage's best iterate that early stopping returns to (the split and the error measures are
:mod:`napari_fdt.recon.assess.validation`'s).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch

from napari_fdt.model.render import iter_batches
from napari_fdt.recon.assess.validation import BestIterate, errors_from_sums, image_error_sums, per_image_errors, relative_image_error
from napari_fdt.recon.problem.stages import Stage

if TYPE_CHECKING:
    from napari_fdt.recon.loop.interface import Run
    from napari_fdt.recon.loop.snapshot import StageRecord

__all__ = ["validation_error", "validation", "image_errors", "track_validation", "end_on_best"]


def validation_error(rec: Run, stage: Stage, mask: torch.Tensor | None = None) -> float | None:
    """Relative RMS error of the held-out images at ``stage`` (None without a validation split).

    Predicted through the current volume with their positions as fitted to their own images (a fit that never
    reaches the volume) and their gains refitted in closed form; ``mask`` (N, h_f, w_f) as the loss's. Every
    rank computes the same number (no collective; in a distributed run after the rows are shared).
    """
    out = validation(rec, stage, mask)
    return None if out is None else out[0]


def validation(rec: Run, stage: Stage, mask: torch.Tensor | None, per_image: bool = False) -> tuple[float, list[float]] | None:
    """(validation error, each held-out image's error (empty unless asked)); None without a split."""
    held = rec.validation_indices
    if not len(held):
        return None
    return image_errors(rec, stage, held, mask, per_image)


def image_errors(rec: Run, stage: Stage, indices: np.ndarray, mask: torch.Tensor | None,
                 per_image: bool = True) -> tuple[float, list[float]]:
    """(relative error of the images ``indices`` predicted through the current state, each one's (empty unless
    ``per_image``)), their gains refitted in closed form (the fit is invariant to a scale per image).

    In a distributed run every rank must call this at the same point (collectives): the rows are shared first (a capture
    of the state then holds every image's), each rank predicts the images it owns (whose rows it trains), and the
    per-image sums are added over ranks, so every rank gets the same numbers (and its decisions the same outcome)."""
    group = rec.group
    if group is not None:
        rec._share_per_source_rows()
        own = indices % group.world_size == group.rank
        sums = torch.zeros(len(indices), 2, dtype=torch.float64, device=rec.device)
        if own.any():
            sums[torch.as_tensor(own, device=rec.device)] = _predicted_error_sums(rec, stage, indices[own], mask)
        err, each = errors_from_sums(group.sum(sums))
        return err, each if per_image else []
    with torch.no_grad():
        dn = rec.volume.delta_n()
        preds = [rec._predict_normalised(stage, dn, torch.as_tensor(indices[sl], device=rec.device))
                 for sl in iter_batches(len(indices), rec.config.batch_size)]
    idx = torch.as_tensor(indices, device=rec.device)
    pred, measured, m = torch.cat(preds), stage.images[idx], None if mask is None else mask[idx]
    each = per_image_errors(pred, measured, m, fit_gain=True) if per_image else []
    return relative_image_error(pred, measured, m, fit_gain=True), each


def _predicted_error_sums(rec: Run, stage: Stage, indices: np.ndarray, mask: torch.Tensor | None) -> torch.Tensor:
    """:func:`~napari_fdt.recon.assess.validation.image_error_sums` (B, 2) of the images ``indices`` (gains refitted)."""
    with torch.no_grad():
        dn = rec.volume.delta_n()
        out = []
        for sl in iter_batches(len(indices), rec.config.batch_size):
            idx = torch.as_tensor(indices[sl], device=rec.device)
            out.append(image_error_sums(rec._predict_normalised(stage, dn, idx), stage.images[idx],
                                        None if mask is None else mask[idx], fit_gain=True))
    return torch.cat(out)


def track_validation(rec: Run, stage: Stage, mask: torch.Tensor | None, best: BestIterate, it: int) -> float | None:
    """The validation error now, recorded in ``best`` (with a copy of the state when it is the lowest yet)."""
    val = rec.validation_error(stage, mask)  # through the method: a test may script the signal there
    if val is not None and rec.config.early_stopping != "off":
        best.update(it, val, rec._capture)
    return val


def end_on_best(rec: Run, stage: Stage, mask: torch.Tensor | None, best: BestIterate, it: int, record: StageRecord) -> float | None:
    """The stage's final validation error; with early stopping, first return to the stage's best iterate when the
    last one is worse than it by more than the tolerance. Fills the record's validation fields."""
    val = track_validation(rec, stage, mask, best, it)
    record.best_iteration = it
    if val is not None and rec.config.early_stopping != "off" and val > best.best_error * (1.0 + best.tolerance):
        rec._restore(best.state, keep_bookkeeping=True)
        val, record.best_iteration = best.best_error, best.best_iteration
    record.validation_error = val
    return val
