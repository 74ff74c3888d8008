"""The least-squares gain of a predicted image against a measured one (a fluorophore's brightness is unknown)."""

from __future__ import annotations

import torch

__all__ = ["least_squares_gain"]

#: Floor of the denominator ``Σ m·pred²``: a blank prediction gets gain 0, not a division by zero.
_TINY = 1e-30


def least_squares_gain(pred: torch.Tensor, measured: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """``argmin_g Σ m·(g·pred − measured)²`` per image: ``Σ m·pred·measured / Σ m·pred²``.

    ``pred``, ``measured`` and ``mask`` (0/1 weights, None: all pixels) are (..., H, W) in any units; the
    gains are (...) in units of measured/pred. The sums run over the last two axes, in the inputs' dtype.
    """
    prod, sq = pred * measured, pred * pred
    if mask is not None:
        prod, sq = prod * mask, sq * mask
    return prod.sum(dim=(-2, -1)) / sq.sum(dim=(-2, -1)).clamp_min(_TINY)
