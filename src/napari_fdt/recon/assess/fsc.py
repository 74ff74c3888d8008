"""Fourier shell correlation (FSC) of two volumes, lateral and axial, and the resolution it gives.

Two Δn volumes ``a``, ``b`` of shape ``(Z, Y, X)`` (slice spacing ``slice_spacing_um``, pixel ``pixel_size_um``) are
compared per spatial frequency in cycles/µm:

* **lateral**: rings of the lateral frequency ``k_xy = sqrt(k_x² + k_y²)`` (width ``1 / (max(Y, X) · pixel)``, up to the
  lateral Nyquist ``0.5 / pixel``), summed over every axial frequency;
* **axial**: planes of ``|k_z|`` (one per slice-grid frequency up to ``0.5 / slice``), summed over every lateral
  frequency (a volume of few slices has few: 8 slices give 5, 0 included).

``FSC(k) = Σ Re(A B*) / sqrt(Σ |A|² Σ |B|²)`` over a bin. Before the transform each volume has its mean removed and is
tapered to zero over the outer eighth of each lateral side (a cosine edge: the transform's wrap-around would otherwise
correlate the two volumes' edges); the axis of few slices is not tapered.

Resolution: the period ``1 / k`` (µm) where the curve first falls below a threshold. For two **half-set**
reconstructions (each from half of the images) the threshold is :data:`HALF_SET_THRESHOLD` (1/7): the full volume then
correlates with the truth at about 0.5 (Rosenthal & Henderson 2003, J. Mol. Biol. 333:721; :func:`truth_fsc_from_halves`).
A curve that never falls below it gives no figure finer than the grid: the volume is resolved up to the grid's
Nyquist period (two pixels, two slices), which is then the bound reported. No torch: numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["HALF_SET_THRESHOLD", "TRUTH_THRESHOLD", "FscCurve", "fsc_curves", "truth_fsc_from_halves", "Resolution", "resolution", "resolutions"]

#: FSC between two half-set volumes at which the full volume's FSC with the truth is about 0.5.
HALF_SET_THRESHOLD = 1.0 / 7.0
#: FSC of a volume with the truth that marks its resolution (the test of the half-set figure against the truth).
TRUTH_THRESHOLD = 0.5


@dataclass(frozen=True)
class FscCurve:
    """One direction's FSC: ``frequency_per_um`` (bins' centres, cycles/µm, from 0), ``correlation`` and ``n_voxels``
    (Fourier voxels per bin), and the grid's Nyquist period ``grid_limit_um`` (µm)."""

    frequency_per_um: np.ndarray
    correlation: np.ndarray
    n_voxels: np.ndarray
    grid_limit_um: float

    def to_dict(self) -> dict[str, Any]:
        return {"frequency_per_um": [round(float(k), 5) for k in self.frequency_per_um],
                "correlation": [round(float(c), 4) for c in self.correlation],
                "n_voxels": [int(n) for n in self.n_voxels], "grid_limit_um": self.grid_limit_um}


def _taper(shape: tuple[int, int, int]) -> np.ndarray:
    """(1, Y, X) weights: 1 inside, a cosine edge over the outer eighth of each lateral side."""
    profiles = []
    for n in shape[1:]:
        m = max(1, n // 8)
        edge = 0.5 - 0.5 * np.cos(np.pi * (np.arange(m) + 0.5) / m)
        prof = np.ones(n)
        prof[:m], prof[n - m:] = edge, edge[::-1]
        profiles.append(prof)
    return (profiles[0][:, None] * profiles[1][None, :])[None]


def _binned(index: np.ndarray, n_bins: int, cross: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    keep = index < n_bins
    i = index[keep]
    num = np.bincount(i, cross[keep], n_bins)
    den = np.sqrt(np.bincount(i, pa[keep], n_bins) * np.bincount(i, pb[keep], n_bins))
    corr = np.divide(num, den, out=np.zeros(n_bins), where=den > 0)
    return corr, np.bincount(i, minlength=n_bins)


def fsc_curves(a: np.ndarray, b: np.ndarray, pixel_size_um: float, slice_spacing_um: float) -> dict[str, FscCurve]:
    """``{"lateral": FscCurve, "axial": FscCurve}`` of two ``(Z, Y, X)`` volumes (module docstring)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(f"two volumes of one (Z, Y, X) shape are needed, got {a.shape} and {b.shape}")
    w = _taper(a.shape)
    fa, fb = np.fft.fftn((a - a.mean()) * w), np.fft.fftn((b - b.mean()) * w)
    cross, pa, pb = (fa * fb.conj()).real, np.abs(fa) ** 2, np.abs(fb) ** 2
    nz, ny, nx = a.shape
    ky = np.fft.fftfreq(ny, pixel_size_um)[:, None]
    kx = np.fft.fftfreq(nx, pixel_size_um)[None, :]
    dk = 1.0 / (max(ny, nx) * pixel_size_um)
    n_lat = int(np.floor(0.5 / pixel_size_um / dk + 1e-9)) + 1
    ring = np.broadcast_to(np.rint(np.sqrt(kx**2 + ky**2) / dk).astype(np.int64)[None], a.shape)
    lat, n_l = _binned(ring.ravel(), n_lat, cross.ravel(), pa.ravel(), pb.ravel())
    plane = np.broadcast_to(np.abs(np.rint(np.fft.fftfreq(nz) * nz)).astype(np.int64)[:, None, None], a.shape)
    n_ax = nz // 2 + 1
    ax, n_a = _binned(plane.ravel(), n_ax, cross.ravel(), pa.ravel(), pb.ravel())
    return {"lateral": FscCurve(np.arange(n_lat) * dk, lat, n_l, 2.0 * pixel_size_um),
            "axial": FscCurve(np.arange(n_ax) / (nz * slice_spacing_um), ax, n_a, 2.0 * slice_spacing_um)}


def truth_fsc_from_halves(fsc_halves: np.ndarray) -> np.ndarray:
    """The full volume's expected FSC with the truth from the halves' FSC: ``sqrt(2F / (1 + F))`` (F < 0 taken as 0)."""
    f = np.clip(np.asarray(fsc_halves, dtype=np.float64), 0.0, 1.0)
    return np.sqrt(2.0 * f / (1.0 + f))


@dataclass(frozen=True)
class Resolution:
    """Where an FSC curve first falls below ``threshold``: the period ``resolution_um`` (µm), or None when it never
    does up to the grid's Nyquist (``grid_limit_um``: the volume is resolved to its grid, and that is the bound)."""

    resolution_um: float | None
    grid_limit_um: float
    threshold: float

    @property
    def bound_um(self) -> float:
        """The figure to show: the resolution, or the grid's Nyquist period where the curve stays above the threshold."""
        return self.grid_limit_um if self.resolution_um is None else self.resolution_um

    def describe(self) -> str:
        if self.resolution_um is None:
            return f"≤ {self.grid_limit_um:.2g} µm (the grid)"
        return f"{self.resolution_um:.2g} µm"

    def to_dict(self) -> dict[str, Any]:
        return {"resolution_um": self.resolution_um, "grid_limit_um": self.grid_limit_um, "threshold": round(self.threshold, 4),
                "resolved_to_grid": self.resolution_um is None}


def resolution(curve: FscCurve, threshold: float) -> Resolution:
    """The period (µm) where ``curve`` first falls below ``threshold`` after its zero-frequency bin, the crossing
    interpolated linearly in frequency between bins; the curve's first bin is never a resolution (the mean)."""
    k, c = curve.frequency_per_um, curve.correlation
    for i in range(1, len(c)):
        if c[i] < threshold:
            c0, c1 = c[i - 1], c[i]
            t = 0.0 if c0 <= threshold else (c0 - threshold) / (c0 - c1)
            k_cross = k[i - 1] + t * (k[i] - k[i - 1])
            k_cross = k_cross if k_cross > 0 else k[1]  # below the threshold from the start: the coarsest period measured
            return Resolution(float(1.0 / k_cross), curve.grid_limit_um, threshold)
    return Resolution(None, curve.grid_limit_um, threshold)


def resolutions(a: np.ndarray, b: np.ndarray, pixel_size_um: float, slice_spacing_um: float,
                threshold: float) -> dict[str, Resolution]:
    """``{"lateral": …, "axial": …}``: where the FSC of ``a`` and ``b`` first falls below ``threshold``."""
    return {d: resolution(c, threshold) for d, c in fsc_curves(a, b, pixel_size_um, slice_spacing_um).items()}
