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
* At the camera the pupil's soft edge (width ``2·pupil_taper·NA/λ``) leaves diffraction tails beyond each
  source's defocused disc; they decay over about ``u = λ/(2·pupil_taper·NA)``. The periodic copies' discs
  must end ``PUPIL_TAIL_UNITS·u`` beyond the image: ``L >= W/2 + max|x_s| + |h_c|·tan(asin(s_lo)) +
  PUPIL_TAIL_UNITS·u`` with ``h_c = max depth + T − image_plane_um`` (the source–focal plane distance).
  Without it, small low-NA geometries lose 1.5–2.6 % of image accuracy to wrap-around (``docs/physics.md``).

Problems the window cannot fix are reported as :class:`~napari_fdt.errors.FDTWarning` at planning time
(``docs/physics.md``, "Warnings before a run"): an undersampled pupil, a grid whose Nyquist frequency cuts
the sources' band limit, evanescent frequencies on the grid, very thin slices, a hard pupil edge, and a
window capped at :data:`MAX_PADDED_SIDE` before it holds the pupil's tails.

Sizes are rounded up to even 2·3·5-smooth numbers (fast FFTs). Lengths in µm, frequencies in cycles/µm.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.physics.optics import Optics

__all__ = [
    "GridPlan", "plan_grid", "plan_for_sources", "next_fast_even", "frequency_grid",
    "DEFAULT_TAPER", "DEFAULT_PUPIL_TAPER", "MAX_SINE", "PUPIL_TAIL_UNITS", "MIN_ROLL_OFF_ON_GRID",
]

#: Width of the raised-cosine roll-off beyond the pupil, in units of the sine of the angle.
DEFAULT_TAPER = 0.1
#: The roll-off ends at most at this sine (the 1/kz factor of a point source diverges at 90°).
MAX_SINE = 0.98
#: Half-width of the pupil's raised-cosine edge, relative to NA/λ.
DEFAULT_PUPIL_TAPER = 0.03
#: Largest padded side we accept (beyond it the geometry is almost certainly a unit mistake).
MAX_PADDED_SIDE = 16384
#: Clearance beyond the periodic copies' defocused discs at the camera, in units of λ/(2·pupil_taper·NA).
#: Measured (homogeneous medium, relative L2 image error against a 6× wider window): 0.45 units (the old
#: rule on 32×32 px of 0.5 µm, NA 0.5, sources 20 µm deep) 2.6 %; 1 unit 0.18 %; 1.5 units 0.11 %.
PUPIL_TAIL_UNITS = 1.0
#: Warn when the grid's Nyquist frequency keeps less than this fraction of the sources' roll-off
#: (f_lo … f_hi). Measured on a Δn 0.02–0.1 bead (image error against a grid twice as fine): fraction 0.64 →
#: 0.1–0.9 %, 0.47 → 0.3–1.8 %, 0.30 → 1.0–3.7 %, 0.02 → 3–8 %.
MIN_ROLL_OFF_ON_GRID = 0.5


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


def _fast_even_up_to(n: int, limit: int) -> int:
    """:func:`next_fast_even` of ``n`` where ``n ≤ limit``; ``n`` itself above (a window refused or capped by the
    caller: the search would walk the gaps between 5-smooth numbers near an absurd size, 1e16 px for a focal plane
    given in metres)."""
    return next_fast_even(n) if n <= limit else int(n)


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
    if max(h, w) + 2 > MAX_PADDED_SIDE:
        raise FDTInputError(
            "images", f"images of {h}x{w} px need a window wider than {MAX_PADDED_SIDE} px",
            f"crop or bin the images to at most {MAX_PADDED_SIDE // 2} px per side (the window also holds the light cone)",
        )
    tan_lo = s_lo / math.sqrt(1.0 - s_lo**2)
    thickness = optics.thickness_um
    margin = thickness * tan_lo
    max_depth_um = float(max_depth_um)
    if not math.isfinite(max_depth_um) or max_depth_um <= 0:
        raise FDTInputError("sources_um", f"largest depth must be positive, got {max_depth_um!r}", "depths are below the volume's bottom face")
    tan_hi = s_hi / math.sqrt(1.0 - s_hi**2)
    reach = (max_depth_um + thickness) * tan_hi
    # Defocused disc of the pupil-filtered field at the camera's focal plane, and the reach of its edge's tails.
    h_cam = abs(max_depth_um + thickness - optics.image_plane_um)
    tail_um = PUPIL_TAIL_UNITS * lam / (2.0 * pupil_taper * optics.na) if pupil_taper > 0 else 0.0
    pupil_reach = h_cam * tan_lo + tail_um
    messages = []
    padded = []
    capped = []
    for n_pix, offset_um in zip((h, w), max_source_offset_um):
        half_image = (n_pix // 2) * dx + dx  # conservative: the far edge of the image
        need_um = max(n_pix * dx + 2 * margin, half_image + margin + abs(float(offset_um)) + reach)
        n_pad = _fast_even_up_to(max(n_pix + 2, math.ceil(need_um / dx - 1e-9)), MAX_PADDED_SIDE)
        if n_pad > MAX_PADDED_SIDE:
            raise FDTInputError(
                "sources_um",
                f"the geometry needs a {n_pad}-pixel window ({need_um:.0f} µm): sources {max_depth_um:g} µm deep "
                f"at NA {optics.na:g} light a cone far wider than the image",
                "check the units (µm) of depth, pixel_size_um and slice_spacing_um, or crop the source range",
            )
        tail_need_um = half_image + abs(float(offset_um)) + pupil_reach
        n_tail = _fast_even_up_to(max(n_pad, math.ceil(tail_need_um / dx - 1e-9)), MAX_PADDED_SIDE)
        if n_tail > MAX_PADDED_SIDE:
            clearance = MAX_PADDED_SIDE * dx - (half_image + abs(float(offset_um)) + h_cam * tan_lo)
            capped.append((n_tail, max(0.0, clearance)))
            n_tail = MAX_PADDED_SIDE
        padded.append(n_tail)
    if capped:
        n_tail, clearance = max(capped)
        messages.append(
            f"sources_um: the window is capped at {MAX_PADDED_SIDE} px ({MAX_PADDED_SIDE * dx:.0f} µm) where the "
            f"pupil's edge needs {n_tail} px: the periodic copies of the sources end {clearance:.0f} µm beyond the "
            f"image instead of {tail_um:.0f} µm (λ/(2·{pupil_taper:g}·NA)), so their diffraction tails wrap onto "
            "the images (1.5–2.6 % image error measured at 0.45 of the clearance); crop the images or the source "
            "range, or check the units (µm) of the depths"
        )
    if pupil_taper == 0:
        messages.append(
            "pupil_taper 0: a hard pupil edge diffracts into tails that no periodic window holds (4.4 % image "
            "error on the letters scene at the planned window, 1.6 % at 2.4× wider; docs/physics.md); "
            f"use the default {DEFAULT_PUPIL_TAPER:g}"
        )
    f_lo = n_b * s_lo / lam
    f_hi = n_b * s_hi / lam
    f_nyquist = 1.0 / (2.0 * dx)
    if optics.na / lam > f_nyquist:
        messages.append(
            f"pixel_size_um {dx:g} undersamples the pupil: NA/λ = {optics.na / lam:.3f} /µm exceeds the Nyquist "
            f"frequency {f_nyquist:.3f} /µm (pixel must be <= λ/(2·NA) = {lam / (2 * optics.na):.3f} µm); "
            "fine detail aliases in the model as in the camera"
        )
    elif f_nyquist < f_lo + MIN_ROLL_OFF_ON_GRID * (f_hi - f_lo):
        kept = max(0.0, (f_nyquist - f_lo) / (f_hi - f_lo))
        s_grid = lam / (2.0 * dx * n_b)
        messages.append(
            f"pixel_size_um {dx:g}: the grid's Nyquist frequency 1/(2·dx) = {f_nyquist:.3f} /µm cuts the sources' "
            f"band limit ({f_lo:.3f}–{f_hi:.3f} /µm), keeping {100 * kept:.0f} % of its roll-off: source light "
            f"beyond sin θ = {s_grid:.3f} is not represented, so what the sample scatters from it into the pupil is "
            f"lost (image errors of 0.3–8 % for Δn 0.02–0.1 measured; docs/physics.md); a pixel of at most "
            f"{1.0 / (2 * (f_lo + MIN_ROLL_OFF_ON_GRID * (f_hi - f_lo))):.3f} µm avoids it (resample the images)"
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
