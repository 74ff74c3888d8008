"""Computational grid for the forward model: padding, band limit and frequency coordinates.

The padded grid is derived from the geometry, not from a fixed factor (``docs/physics.md``,
section "Grid and band limit"):

* The pupil's edge is a raised cosine from ``(1 − pupil_taper)·NA/λ`` to ``(1 + pupil_taper)·NA/λ``
  (a hard edge diffracts into tails that no finite periodic window holds: 4 % image error at the
  planned window, 0.06 % with a 3 % taper; ``docs/physics.md``).
* ``s_lo = (1 + pupil_taper)·na / n_background`` is the sine of the largest angle the pupil passes; the
  point-source spectrum is exact up to ``f_lo = n_b·s_lo/λ``.
* ``s_hi = min(s_lo + taper, 0.98)`` ends a raised-cosine roll-off at ``f_hi = n_b * s_hi / wavelength``.
* Light that reaches the image through the pupil crossed the volume within ``p = T * tan(asin(s_lo))``
  of the image (``T`` the volume thickness): the window holds the image plus ``p`` per side.
* The window period ``L`` must keep the periodic images of every source outside the band limit's cone
  over the image and its margin: ``L >= W/2 + p + max|x_s| + (max depth + T) * tan(asin(s_hi))``.

Sizes are rounded up to even 2·3·5-smooth numbers (fast FFTs). Lengths in µm, frequencies in cycles/µm.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from .errors import FDTInputError, FDTWarning
from .optics import Optics

__all__ = [
    "GridPlan", "plan_grid", "plan_for_sources", "next_fast_even", "frequency_grid",
    "DEFAULT_TAPER", "DEFAULT_PUPIL_TAPER", "MAX_SINE",
]

#: Width of the raised-cosine roll-off beyond the pupil, in units of the sine of the angle.
DEFAULT_TAPER = 0.1
#: The roll-off ends at most at this sine (the 1/kz factor of a point source diverges at 90°).
MAX_SINE = 0.98
#: Half-width of the pupil's raised-cosine edge, relative to NA/λ.
DEFAULT_PUPIL_TAPER = 0.03
#: Largest padded side we accept (beyond it the geometry is almost certainly a unit mistake).
MAX_PADDED_SIDE = 16384


def next_fast_even(n: int) -> int:
    """Smallest even integer >= ``n`` whose only prime factors are 2, 3 and 5."""
    n = max(2, int(n))
    while True:
        if n % 2 == 0:
            m = n
            for p in (2, 3, 5):
                while m % p == 0:
                    m //= p
            if m == 1:
                return n
        n += 1


@dataclass(frozen=True)
class GridPlan:
    """Where and how the forward model samples the field.

    Attributes
    ----------
    image_shape: (H, W) of the camera images and of each RI slice.
    padded_shape: (Hp, Wp) of the computational window, even.
    offset: (row, col) of image pixel (0, 0) inside the window; ``offset = padded // 2 - image // 2``.
    pixel_size_um: sampling, µm.
    pupil_taper: half-width of the pupil's soft edge relative to NA/λ (0: hard edge).
    f_lo_per_um: outer pupil edge (1 + pupil_taper)·NA/λ, cycles/µm; the source spectrum is exact below it.
    f_hi_per_um: end of the raised-cosine roll-off, cycles/µm.
    margin_um: (y, x) lateral margin ``p`` the volume's light cone needs around the image, µm.
    warnings: the sampling problems found (also emitted as :class:`FDTWarning`).
    """

    image_shape: tuple[int, int]
    padded_shape: tuple[int, int]
    offset: tuple[int, int]
    pixel_size_um: float
    pupil_taper: float
    f_lo_per_um: float
    f_hi_per_um: float
    margin_um: float
    warnings: tuple[str, ...] = field(default=())

    @property
    def padding_factor(self) -> float:
        """Area of the window over the area of the image."""
        return (self.padded_shape[0] * self.padded_shape[1]) / (self.image_shape[0] * self.image_shape[1])


def plan_grid(
    optics: Optics,
    image_shape: tuple[int, int],
    max_source_offset_um: tuple[float, float],
    max_depth_um: float,
    *,
    taper: float = DEFAULT_TAPER,
    pupil_taper: float = DEFAULT_PUPIL_TAPER,
    warn: bool = True,
) -> GridPlan:
    """Plan the padded window and band limit for a geometry.

    Parameters
    ----------
    optics: the optics and sampling.
    image_shape: (H, W) in pixels.
    max_source_offset_um: largest |y| and |x| of any source from the image centre, µm.
    max_depth_um: largest source depth below the volume's bottom face, µm.
    taper: width of the source's roll-off in sine units (default :data:`DEFAULT_TAPER`).
    pupil_taper: half-width of the pupil's soft edge relative to NA/λ (default :data:`DEFAULT_PUPIL_TAPER`).
    warn: emit :class:`FDTWarning` for each sampling problem found.
    """
    h, w = (int(s) for s in image_shape)
    dx = optics.pixel_size_um
    lam = optics.wavelength_um
    n_b = optics.n_background
    if not (0.0 < taper < 1.0):
        raise FDTInputError("taper", f"must be in (0, 1), got {taper!r}", "use the default 0.1")
    if not (0.0 <= pupil_taper < 0.5):
        raise FDTInputError("pupil_taper", f"must be in [0, 0.5), got {pupil_taper!r}", "use the default 0.03, or 0 for a hard edge")
    s_lo = (1.0 + pupil_taper) * optics.na / n_b
    s_hi = min(s_lo + taper, MAX_SINE)
    if s_hi - s_lo < 0.02:
        raise FDTInputError(
            "na",
            f"na/n_background = {optics.na / n_b:.3f} leaves no room for a smooth band limit below {MAX_SINE}",
            f"na must be at most {(MAX_SINE - 0.02) * n_b / (1.0 + pupil_taper):.3f} for n_background {n_b:g}",
        )
    tan_lo = s_lo / math.sqrt(1.0 - s_lo**2)
    thickness = optics.thickness_um
    margin = thickness * tan_lo
    max_depth_um = float(max_depth_um)
    if not math.isfinite(max_depth_um) or max_depth_um <= 0:
        raise FDTInputError("sources_um", f"largest depth must be positive, got {max_depth_um!r}", "depths are below the volume's bottom face")
    tan_hi = s_hi / math.sqrt(1.0 - s_hi**2)
    reach = (max_depth_um + thickness) * tan_hi
    padded = []
    for n_pix, offset_um in zip((h, w), max_source_offset_um):
        half_image = (n_pix // 2) * dx + dx  # conservative: the far edge of the image
        need_um = max(n_pix * dx + 2 * margin, half_image + margin + abs(float(offset_um)) + reach)
        n_pad = next_fast_even(max(n_pix + 2, math.ceil(need_um / dx - 1e-9)))
        if n_pad > MAX_PADDED_SIDE:
            raise FDTInputError(
                "sources_um",
                f"the geometry needs a {n_pad}-pixel window ({need_um:.0f} µm): sources {max_depth_um:g} µm deep "
                f"at NA {optics.na:g} light a cone far wider than the image",
                "check the units (µm) of depth, pixel_size_um and slice_spacing_um, or crop the source range",
            )
        padded.append(n_pad)
    messages = []
    f_lo = n_b * s_lo / lam
    f_hi = n_b * s_hi / lam
    f_nyquist = 1.0 / (2.0 * dx)
    if optics.na / lam > f_nyquist:
        messages.append(
            f"pixel_size_um {dx:g} undersamples the pupil: NA/λ = {optics.na / lam:.3f} /µm exceeds the Nyquist "
            f"frequency {f_nyquist:.3f} /µm (pixel must be <= λ/(2·NA) = {lam / (2 * optics.na):.3f} µm); "
            "fine detail aliases in the model as in the camera"
        )
    if n_b / lam < f_nyquist:
        messages.append(
            f"pixel_size_um {dx:g} is finer than λ/(2·n_b) = {lam / (2 * n_b):.3f} µm: the grid holds evanescent "
            "frequencies; the model drops them (they cannot reach the camera)"
        )
    if optics.slice_spacing_um < lam / n_b / 4:
        messages.append(
            f"slice_spacing_um {optics.slice_spacing_um:g} is below λ/(4·n_b): slices thinner than the axial "
            "resolution add cost without information"
        )
    if warn:
        for m in messages:
            warnings.warn(m, FDTWarning, stacklevel=2)
    hp, wp = padded
    return GridPlan(
        image_shape=(h, w),
        padded_shape=(hp, wp),
        offset=(hp // 2 - h // 2, wp // 2 - w // 2),
        pixel_size_um=dx,
        pupil_taper=float(pupil_taper),
        f_lo_per_um=f_lo,
        f_hi_per_um=f_hi,
        margin_um=margin,
        warnings=tuple(messages),
    )


def plan_for_sources(optics: Optics, image_shape: tuple[int, int], sources_um: np.ndarray, **kwargs) -> GridPlan:
    """:func:`plan_grid` for an array of sources (N, 3) = (x, y, depth) in µm."""
    src = np.asarray(sources_um, dtype=np.float64).reshape(-1, 3)
    return plan_grid(
        optics,
        image_shape,
        (float(np.abs(src[:, 1]).max()), float(np.abs(src[:, 0]).max())),
        float(src[:, 2].max()),
        **kwargs,
    )


def frequency_grid(
    padded_shape: tuple[int, int], pixel_size_um: float | torch.Tensor, *, device=None, dtype=torch.float32
) -> tuple[torch.Tensor, torch.Tensor]:
    """Spatial frequencies (fy, fx) of the unshifted FFT of the window, cycles/µm, shapes (Hp, 1) and (1, Wp).

    ``pixel_size_um`` may be a tensor (differentiable).
    """
    hp, wp = padded_shape
    fy = torch.fft.fftfreq(hp, device=device, dtype=dtype).reshape(hp, 1)
    fx = torch.fft.fftfreq(wp, device=device, dtype=dtype).reshape(1, wp)
    return fy / pixel_size_um, fx / pixel_size_um
