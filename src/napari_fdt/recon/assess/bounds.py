"""A per-voxel error bound of a volume from its re-simulated reconstructions (``error_bounds``; issue 50).

The run's result R is used as if it were the truth: images are simulated from it (its calibrated sources, gains and
optics, fresh noise at the data's level) and reconstructed along the run's own path, K times
(:mod:`napari_fdt.recon.run.error_bounds`). How the pipeline distorts R shows how it distorted the truth: the
replicates' mean offset from R (the bias: axial elongation, fill-in, lost contrast) and their spread (the noise).
The raw score is that bias plus spread, divided by the share of R's contrast the replicates keep (where the pipeline
keeps a share λ of a volume like R, R is itself about λ × the truth, and the bias seen on R understates R's error by
1/λ), taken as the largest over a neighbourhood (an error sits beside where the bias estimate puts it; the
missing cone spreads it along z), plus a share of the neighbourhood's largest |R| (what a bias estimate from R cannot
see: structure R lost altogether scales with the structure near it). The bound is a constant times the score,
the constant set by split-conformal calibration on simulated scenes (:data:`CALIBRATION`): it holds on about
``level`` of the voxels of scenes like those, and nowhere else is it promised.

Arrays are Δn (RI units), ``(n_slices, H, W)``; the bound has the volume's grid and units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = ["REPLICATES", "BoundCalibration", "CALIBRATION", "raw_score", "bound", "conformal_quantile", "retention", "MIN_RETENTION",
           "neighbourhood_max"]


#: Re-simulated reconstructions per bound.
REPLICATES = 2


@dataclass(frozen=True)
class BoundCalibration:
    """How the raw score becomes a bound: the neighbourhood (``slices``, ``pixels``: the max filter's extent), the
    contrast share ``alpha`` and the conformal factor ``q`` (bound = q · score) at coverage ``level``; ``scenes``
    and ``source`` say where q was measured."""

    slices: int
    pixels: int
    alpha: float
    deflate: bool
    q: float
    level: float
    scenes: int
    source: str


#: The calibration in use: the score chosen and q measured on 16 simulated scenes of four families (beads, cells,
#: fibres in 3 µm slices, letters; 48² px of 0.33 µm, 6 slices; made with 4 sub-slices and the 2× field grid), then
#: tested on 16 others (docs/decisions/error-bounds.md; ``python -m benchmarks run error_bounds table``).
CALIBRATION = BoundCalibration(slices=5, pixels=9, alpha=0.8, deflate=True, q=0.3043, level=0.9, scenes=16,
                               source="benchmarks/error_bounds.py, even seeds 0-6 of beads, cells, fibres, letters (2026-11-28)")


def neighbourhood_max(a: np.ndarray, slices: int, pixels: int) -> np.ndarray:
    """The largest of ``a`` over ``slices`` × ``pixels`` × ``pixels`` voxels around each voxel (edges: nearest)."""
    if slices <= 1 and pixels <= 1:
        return a
    return ndimage.maximum_filter(a, size=(max(1, slices), max(1, pixels), max(1, pixels)), mode="nearest")


#: Least contrast retention :func:`raw_score` divides by (a replicate keeping a tenth of R's contrast or less)
MIN_RETENTION = 0.1


def retention(result: np.ndarray, replicates: np.ndarray, slices: int, pixels: int) -> np.ndarray:
    """The share of R's contrast the pipeline keeps, per voxel: Σ|mean_k R_k| / Σ|R| over the neighbourhood, in
    [MIN_RETENTION, 1]. Where the pipeline keeps a share λ of a volume like R, R itself is about λ × the truth, so
    the bias it shows on R (|R_k − R|) understates R's own error by about 1/λ."""
    size = (max(1, slices), max(1, pixels), max(1, pixels))
    kept = ndimage.uniform_filter(np.abs(replicates.mean(axis=0)), size=size, mode="nearest")
    had = ndimage.uniform_filter(np.abs(result), size=size, mode="nearest")
    return np.clip(kept / np.maximum(had, 1e-12), MIN_RETENTION, 1.0)


def raw_score(result: np.ndarray, replicates: np.ndarray, *, slices: int, pixels: int, alpha: float,
              deflate: bool = False) -> np.ndarray:
    """The raw score (module docstring) of ``result`` (n_slices, H, W) from ``replicates`` (K, n_slices, H, W), Δn;
    float64, ≥ 0, the volume's shape. ``deflate``: bias and spread divided by the :func:`retention`."""
    result = np.asarray(result, dtype=np.float64)
    reps = np.asarray(replicates, dtype=np.float64)
    if reps.ndim != 4 or reps.shape[1:] != result.shape or reps.shape[0] < 1:
        raise ValueError(f"replicates must be (K >= 1, {', '.join(map(str, result.shape))}), got {reps.shape}")
    spread = reps.std(axis=0, ddof=1) if reps.shape[0] > 1 else np.zeros_like(result)
    bias = np.abs(reps.mean(axis=0) - result)
    local = bias + spread
    if deflate:
        local = local / retention(result, reps, slices, pixels)
    score = neighbourhood_max(local, slices, pixels)
    if alpha:
        score = score + alpha * neighbourhood_max(np.abs(result), slices, pixels)
    return score + 1e-6


def bound(result: np.ndarray, replicates: np.ndarray, calibration: BoundCalibration = CALIBRATION) -> np.ndarray:
    """The bound U (n_slices, H, W), Δn units, float32: |Δn − Δn_true| ≤ U on about ``calibration.level`` of the
    support of scenes like the calibration's."""
    c = calibration
    return (c.q * raw_score(result, replicates, slices=c.slices, pixels=c.pixels, alpha=c.alpha, deflate=c.deflate)).astype(np.float32)


def conformal_quantile(ratios: np.ndarray, level: float) -> float:
    """Split conformal: the ⌈(n + 1)·level⌉-th smallest of the n calibration ratios |error| / score."""
    r = np.asarray(ratios, dtype=np.float64).ravel()
    n = r.size
    if n == 0:
        raise ValueError("no calibration ratios")
    k = min(n, int(np.ceil((n + 1) * level)))
    return float(np.partition(r, k - 1)[k - 1])
