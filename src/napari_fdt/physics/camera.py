"""The camera: intensity averaged over each pixel's area (pixel integration).

A camera pixel records the intensity integrated over its square area, not the value at its centre. The
intensity ``|E|²`` of a field band-limited by the pupil to ``f_c = (1 + ε)·NA/λ`` has band ``2·f_c``: twice
the field's. When that exceeds the camera's Nyquist frequency ``1/(2·dx)`` the point samples alias and the
area average differs from them (6.7 % on a camera sampling the pupil at Nyquist, ``docs/physics.md`` §3).

Computed exactly in the Fourier domain on the periodic window (:func:`pixel_averaged_intensity`): the field's
spectrum is zero-padded to a grid twice as fine (exact: the field has no content beyond its Nyquist), the
intensity is formed there (its band ``2·f_c`` is below the fine Nyquist ``1/dx`` whenever the field is sampled
at Nyquist, ``dx ≤ λ/(2·f_c·λ)``), multiplied in frequency by the box's transfer function
``sinc(fx·dx)·sinc(fy·dx)`` and sampled at the pixel centres (the fine spectrum folded onto the coarse grid).
The result is the mean intensity over each pixel (same units as a point sample: a smooth image is unchanged).
"""

from __future__ import annotations

import torch

from napari_fdt.errors import FDTInputError

__all__ = ["PIXEL_INTEGRATION_CHOICES", "needs_pixel_integration", "resolve_pixel_integration", "pixel_averaged_intensity",
           "fine_field", "pixel_average_from_fine"]

PIXEL_INTEGRATION_CHOICES = ("auto", True, False)


def needs_pixel_integration(na: float, wavelength_um: float, pixel_size_um: float) -> bool:
    """The physical rule of ``"auto"``: the intensity's band ``2·NA/λ`` exceeds the camera's Nyquist ``1/(2·dx)``."""
    return 2.0 * na / wavelength_um > 1.0 / (2.0 * pixel_size_um)


def resolve_pixel_integration(setting, na: float, wavelength_um: float, pixel_size_um: float) -> bool:
    """``True``/``False`` pass through; ``"auto"`` applies :func:`needs_pixel_integration`."""
    if isinstance(setting, str):
        low = setting.strip().lower()
        if low in ("true", "on", "yes"):
            return True
        if low in ("false", "off", "no"):
            return False
        if low == "auto":
            return needs_pixel_integration(na, wavelength_um, pixel_size_um)
    elif isinstance(setting, bool):
        return setting
    raise FDTInputError("pixel_integration", f"must be \"auto\", true or false, got {setting!r}",
                        "use \"auto\" (on when 2·NA/λ > 1/(2·pixel_size_um)), true or false")


def _pad_spectrum(spec: torch.Tensor) -> torch.Tensor:
    """Unshifted (..., H, W) spectrum (even H, W) → (..., 2H, 2W), zeros at the new high frequencies.

    The Nyquist row/column (index H/2) is split evenly between +H/2 and −H/2 so a real-valued content stays real.
    """
    h, w = spec.shape[-2:]
    hh, hw = h // 2, w // 2
    out = spec.new_zeros((*spec.shape[:-2], 2 * h, 2 * w))
    rows = [(slice(0, hh), slice(0, hh)), (slice(h - hh + 1, h), slice(2 * h - hh + 1, 2 * h))]
    cols = [(slice(0, hw), slice(0, hw)), (slice(w - hw + 1, w), slice(2 * w - hw + 1, 2 * w))]
    for rs, rd in rows:
        for cs, cd in cols:
            out[..., rd, cd] = spec[..., rs, cs]
    # Nyquist row and column: half to each side (zero in practice: the pupil ends below Nyquist)
    ny = spec[..., hh : hh + 1, :]
    nx = spec[..., :, hw : hw + 1]
    for rd in (slice(hh, hh + 1), slice(2 * h - hh, 2 * h - hh + 1)):
        for cs, cd in cols:
            out[..., rd, cd] = out[..., rd, cd] + 0.5 * ny[..., :, cs]
    for cd in (slice(hw, hw + 1), slice(2 * w - hw, 2 * w - hw + 1)):
        for rs, rd in rows:
            out[..., rd, cd] = out[..., rd, cd] + 0.5 * nx[..., rs, :]
    return out


def fine_field(field_spectrum: torch.Tensor) -> torch.Tensor:
    """The field of an unshifted (..., Hp, Wp) spectrum on a grid twice as fine, (..., 2Hp, 2Wp) complex.

    Fine pixel (i, j) sits at coarse position (i/2, j/2): exact for a field with no content at the Nyquist frequency.
    """
    h, w = field_spectrum.shape[-2:]
    if h % 2 or w % 2:
        raise ValueError("the window must have even sizes")
    return torch.fft.ifft2(_pad_spectrum(field_spectrum)) * 4.0  # ifft's 1/N grew 4×


def pixel_average_from_fine(fine: torch.Tensor) -> torch.Tensor:
    """Mean of ``|E|²`` over each coarse pixel from the field on the twice-finer grid; (..., 2Hp, 2Wp) → (..., Hp, Wp)."""
    h, w = fine.shape[-2] // 2, fine.shape[-1] // 2
    intensity = fine.real.square() + fine.imag.square()
    spec = torch.fft.fft2(intensity)
    real = intensity.dtype
    # box of one coarse pixel: transfer sinc(f·dx); the fine grid's frequencies are fftfreq(2n)·2 cycles per dx
    ty = torch.sinc(torch.fft.fftfreq(2 * h, device=spec.device, dtype=real) * 2.0).reshape(2 * h, 1)
    tx = torch.sinc(torch.fft.fftfreq(2 * w, device=spec.device, dtype=real) * 2.0).reshape(1, 2 * w)
    spec = spec * (ty * tx)
    # samples at the pixel centres (even fine indices): fold the four quadrants of the spectrum
    folded = (spec[..., :h, :w] + spec[..., h:, :w] + spec[..., :h, w:] + spec[..., h:, w:]) * 0.25
    return torch.fft.ifft2(folded).real


def pixel_averaged_intensity(field_spectrum: torch.Tensor) -> torch.Tensor:
    """Mean of ``|E|²`` over each pixel of the window, (..., Hp, Wp) real, from the field's unshifted spectrum.

    ``field_spectrum``: ``fft2(E)`` on the periodic window (even sizes), E band-limited below the window's
    Nyquist frequency. Exact (to rounding) when the intensity's band is below ``1/dx``.
    """
    return pixel_average_from_fine(fine_field(field_spectrum))
