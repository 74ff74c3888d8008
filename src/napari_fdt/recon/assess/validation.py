"""Held-out images: which images the solver keeps out of training, and how well the volume predicts them.

The validation error is what a user reads as "how far to trust this volume" when no ground truth exists: the
images of sources the volume was never fitted to, predicted through it (their gains fitted in closed form and their
positions from the initial estimate with the common calibration applied), compared with the loss the solver trains
on. It rises when the volume fills with what the data cannot constrain, while the training error keeps falling.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

from napari_fdt.errors import FDTWarning
from napari_fdt.model.gain import least_squares_gain

__all__ = ["holdout_indices", "split_halves", "spread_picks", "relative_image_error", "per_image_errors", "image_error_sums",
           "errors_from_sums", "BestIterate", "MIN_VALIDATION_IMAGES"]

#: Fewest held-out images a split may have; with fewer, the error of one badly placed source would dominate.
MIN_VALIDATION_IMAGES = 3
#: Most of the acquisition a split may take (the solver must keep most images to train on).
MAX_VALIDATION_SHARE = 0.25


def holdout_indices(sources_um: np.ndarray, fraction: float) -> np.ndarray:
    """Indices (sorted, int64) of the images to hold out, spread evenly over the field of sources.

    ``sources_um``: (N, 3) µm, the initial positions. ``fraction`` of the N images (at least
    :data:`MIN_VALIDATION_IMAGES`, at most a quarter) are spread over the field of sources (:func:`spread_picks`), so
    that the held-out sources cover the field like the rest.
    ``fraction`` 0 gives an empty split; so does an acquisition too small to spare the minimum (with an
    :class:`FDTWarning` saying so).
    """
    src = np.asarray(sources_um, dtype=np.float64)
    n = src.shape[0]
    if fraction <= 0 or n == 0:
        return np.zeros(0, dtype=np.int64)
    k = max(MIN_VALIDATION_IMAGES, int(round(fraction * n)))
    k = min(k, int(math.floor(MAX_VALIDATION_SHARE * n)))
    if k < MIN_VALIDATION_IMAGES:
        warnings.warn(
            f"validation_fraction: {n} images are too few to hold out {MIN_VALIDATION_IMAGES} for validation and "
            f"keep {1 - MAX_VALIDATION_SHARE:.0%} for training; no validation error will be reported",
            FDTWarning, stacklevel=2)
        return np.zeros(0, dtype=np.int64)
    return spread_picks(src[:, :2], k)


def split_halves(sources_um: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Image indices in two halves that each cover the illumination like the whole: the images are paired with their
    nearest neighbour by source position (x, y), one of each pair to each half at random (``seed``); an odd image out
    goes to the first half. Both sorted."""
    src = np.asarray(sources_um, dtype=np.float64)
    rng = np.random.default_rng(seed)
    left = list(rng.permutation(len(src)))
    a: list[int] = []
    b: list[int] = []
    while len(left) > 1:
        i = left.pop(0)
        d = np.hypot(*(src[left, :2] - src[i, :2]).T)
        j = left.pop(int(np.argmin(d)))
        first, second = (a, b) if rng.random() < 0.5 else (b, a)
        first.append(int(i))
        second.append(int(j))
    if left:
        a.append(int(left[0]))
    return np.array(sorted(a), dtype=np.int64), np.array(sorted(b), dtype=np.int64)


def spread_picks(xy: np.ndarray, k: int, lloyd_steps: int = 30) -> np.ndarray:
    """``k`` indices of lateral positions (N, 2) µm spread evenly over them, sorted; deterministic.

    k-means of the positions (Lloyd's iterations, started from the first ``k`` points of the R2 low-discrepancy
    sequence scaled to the positions' bounding box) splits the field into ``k`` cells of about equal numbers of
    sources; each cell's centroid then takes the nearest source not yet taken.
    """
    n = xy.shape[0]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    unit = (xy - lo) / np.where(hi > lo, hi - lo, 1.0)
    g = 1.32471795724474602596  # plastic number: R2 sequence alpha = (1/g, 1/g^2) (Roberts 2018)
    alpha = np.array([1.0 / g, 1.0 / (g * g)])
    centres = (0.5 + np.arange(1, k + 1)[:, None] * alpha) % 1.0
    for _ in range(lloyd_steps):
        owner = np.argmin(((unit[:, None] - centres[None]) ** 2).sum(-1), axis=1)
        for j in range(k):
            if np.any(owner == j):
                centres[j] = unit[owner == j].mean(axis=0)
    free = np.ones(n, dtype=bool)
    out = []
    for c in centres:
        d2 = ((unit - c) ** 2).sum(axis=1)
        d2[~free] = np.inf
        i = int(np.argmin(d2))
        free[i] = False
        out.append(i)
    return np.sort(np.array(out, dtype=np.int64))


def relative_image_error(pred: torch.Tensor, measured: torch.Tensor, mask: torch.Tensor | None = None, *,
                         fit_gain: bool = False) -> float:
    """Relative RMS image error ``sqrt(Σ m·(g·p − y)² / Σ m·y²)`` over a stack (B, H, W), as a float.

    ``fit_gain``: ``g`` per image is the closed-form least-squares gain (held-out images, whose gains were never
    trained); otherwise 1 (the prediction already carries its gain). ``mask`` (B, H, W) or None weights pixels.
    """
    return float(_relative_error(pred, measured, mask, fit_gain))


def _relative_error(pred: torch.Tensor, measured: torch.Tensor, mask: torch.Tensor | None, fit_gain: bool) -> torch.Tensor:
    """:func:`relative_image_error` as a 0-d tensor (no wait for the device)."""
    m = torch.ones_like(measured) if mask is None else mask
    if fit_gain:
        pred = pred * least_squares_gain(pred, measured, mask).clamp_min(0.0)[:, None, None]
    err = ((pred - measured) ** 2 * m).sum()
    ref = (measured * measured * m).sum().clamp_min(1e-30)
    return torch.sqrt(err / ref)


def per_image_errors(pred: torch.Tensor, measured: torch.Tensor, mask: torch.Tensor | None = None, *,
                     fit_gain: bool = False) -> list[float]:
    """:func:`relative_image_error` of each image of a stack (B,), as floats (same gains and mask; the same arithmetic
    image by image, read back from the device once)."""
    if measured.shape[0] == 0:
        return []
    return torch.stack([_relative_error(pred[i:i + 1], measured[i:i + 1], None if mask is None else mask[i:i + 1], fit_gain)
                        for i in range(measured.shape[0])]).tolist()


def image_error_sums(pred: torch.Tensor, measured: torch.Tensor, mask: torch.Tensor | None = None, *,
                     fit_gain: bool = False) -> torch.Tensor:
    """Each image's ``(Σ m·(g·p − y)², Σ m·y²)`` (B, 2) float64: the parts of :func:`relative_image_error` that add
    over images, so that the images can be shared out (a distributed run) and the errors made from the sums
    (:func:`errors_from_sums`)."""
    m = torch.ones_like(measured) if mask is None else mask
    if fit_gain:
        pred = pred * least_squares_gain(pred, measured, mask).clamp_min(0.0)[:, None, None]
    err = ((pred - measured) ** 2 * m).sum(dim=(-2, -1))
    ref = (measured * measured * m).sum(dim=(-2, -1))
    return torch.stack([err, ref], dim=-1).to(torch.float64)


def errors_from_sums(sums: torch.Tensor) -> tuple[float, list[float]]:
    """(the stack's relative error, each image's) from :func:`image_error_sums` (B, 2)."""
    total = torch.sqrt(sums[:, 0].sum() / sums[:, 1].sum().clamp_min(1e-30))
    return float(total), torch.sqrt(sums[:, 0] / sums[:, 1].clamp_min(1e-30)).tolist()


@dataclass
class BestIterate:
    """The lowest validation error seen in a stage, and a copy of the state it was seen at.

    ``update(error, capture)`` records an error; ``capture()`` is called only when it is the best so far (a copy of
    the small optimised tensors). ``stalled(patience)``: the last ``patience`` errors were all above the best by
    more than ``tolerance`` (relative): the volume has started to fit what the held-out images do not confirm.
    """

    tolerance: float = 0.0
    best_error: float = math.inf
    best_iteration: int = -1
    state: Any = None
    errors: list[float] = field(default_factory=list)

    def update(self, iteration: int, error: float, capture: Callable[[], Any]) -> bool:
        """Record ``error`` at ``iteration``; True (and the state captured) when it is the best so far."""
        self.errors.append(float(error))
        if error < self.best_error:
            self.best_error, self.best_iteration, self.state = float(error), int(iteration), capture()
            return True
        return False

    def stalled(self, patience: int) -> bool:
        """True when each of the last ``patience`` errors exceeds the best by more than the tolerance."""
        if patience < 1 or len(self.errors) < patience or not math.isfinite(self.best_error):
            return False
        limit = self.best_error * (1.0 + self.tolerance)
        return all(e > limit for e in self.errors[-patience:])
