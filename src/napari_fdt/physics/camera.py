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


def _quadrants(n: int) -> list[tuple[slice, slice]]:
    """(source, destination) slices along one axis of :func:`_pad_spectrum`: the non-negative and the negative
    frequencies of an even length ``n``, into a length ``2n``."""
    half = n // 2
    return [(slice(0, half), slice(0, half)), (slice(n - half + 1, n), slice(2 * n - half + 1, 2 * n))]


def _pad_forward(spec: torch.Tensor) -> torch.Tensor:
    h, w = spec.shape[-2:]
    hh, hw = h // 2, w // 2
    rows, cols = _quadrants(h), _quadrants(w)
    out = spec.new_zeros((*spec.shape[:-2], 2 * h, 2 * w))
    for rs, rd in rows:
        for cs, cd in cols:
            out[..., rd, cd] = spec[..., rs, cs]
    # Nyquist row and column: half to each side (zero in practice: the pupil ends below Nyquist)
    for rd in (hh, 2 * h - hh):
        for cs, cd in cols:
            out[..., rd, cd] += 0.5 * spec[..., hh, cs]
    for cd in (hw, 2 * w - hw):
        for rs, rd in rows:
            out[..., rd, cd] += 0.5 * spec[..., rs, hw]
    return out


def _pad_adjoint(grad: torch.Tensor) -> torch.Tensor:
    """The adjoint of :func:`_pad_forward` (real coefficients: the same for complex values): the fine grid's
    quadrants gathered back, the Nyquist row and column from both their images."""
    h, w = grad.shape[-2] // 2, grad.shape[-1] // 2
    hh, hw = h // 2, w // 2
    rows, cols = _quadrants(h), _quadrants(w)
    out = grad.new_zeros((*grad.shape[:-2], h, w))
    for rs, rd in rows:
        for cs, cd in cols:
            out[..., rs, cs] = grad[..., rd, cd]
    for cs, cd in cols:
        out[..., hh, cs] = 0.5 * (grad[..., hh, cd] + grad[..., 2 * h - hh, cd])
    for rs, rd in rows:
        out[..., rs, hw] = 0.5 * (grad[..., rd, hw] + grad[..., rd, 2 * w - hw])
    return out


class _PadSpectrum(torch.autograd.Function):
    """:func:`_pad_spectrum` with its adjoint as the backward: plain autograd of the slice assignments clones and
    zero-fills the whole fine-grid gradient once per assignment (12 per call), which made pixel integration cost
    twice the rest of a training step on the CPU."""

    @staticmethod
    def forward(ctx, spec: torch.Tensor) -> torch.Tensor:  # noqa: D102
        return _pad_forward(spec)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:  # noqa: D102
        return _pad_adjoint(grad)


def _pad_spectrum(spec: torch.Tensor) -> torch.Tensor:
    """Unshifted (..., H, W) spectrum (even H, W) → (..., 2H, 2W), zeros at the new high frequencies.

    The Nyquist row/column (index H/2) is split evenly between +H/2 and −H/2 so a real-valued content stays real.
    Differentiable, with the adjoint as its backward (:class:`_PadSpectrum`).
    """
    return _PadSpectrum.apply(spec)


def fine_field(field_spectrum: torch.Tensor) -> torch.Tensor:
    """The field of an unshifted (..., Hp, Wp) spectrum on a grid twice as fine, (..., 2Hp, 2Wp) complex.

    Fine pixel (i, j) sits at coarse position (i/2, j/2): exact for a field with no content at the Nyquist frequency.
    """
    h, w = field_spectrum.shape[-2:]
    if h % 2 or w % 2:
        raise ValueError("the window must have even sizes")
    return torch.fft.ifft2(_pad_spectrum(field_spectrum)) * 4.0  # ifft's 1/N grew 4×


def pixel_average_from_fine(fine: torch.Tensor) -> torch.Tensor:
    """Mean of ``|E|²`` over each coarse pixel from the field on the twice-finer grid; (..., 2Hp, 2Wp) → (..., Hp, Wp).

    The intensity's spectrum times the box's transfer function, sampled at the pixel centres (the even fine indices),
    one axis at a time on real transforms: along x the fine intensity's ``rfft``, the sinc, and the fold onto the
    coarse grid (``Y[c] = (X[c] + X[c + W])/2``, ``X[c + W] = conj(X[W − c])`` for a real signal), which leaves a
    quarter of the fine grid's columns for the transforms along y (the same fold there), then the inverse ones. The
    same numbers as one complex FFT of the whole fine grid (to rounding), at about a third of its cost.
    """
    h, w = fine.shape[-2] // 2, fine.shape[-1] // 2
    intensity = fine.real.square() + fine.imag.square()
    real = intensity.dtype
    # box of one coarse pixel: transfer sinc(f·dx); the fine grid's frequencies are fftfreq(2n)·2 cycles per dx
    tx = torch.sinc(torch.fft.rfftfreq(2 * w, device=fine.device, dtype=real) * 2.0)  # (W + 1,)
    ty = torch.sinc(torch.fft.fftfreq(2 * h, device=fine.device, dtype=real) * 2.0).reshape(2 * h, 1)
    along_x = torch.fft.rfft(intensity, dim=-1) * tx  # (..., 2Hp, Wp + 1)
    half = w // 2
    along_x = 0.5 * (along_x[..., : half + 1] + along_x[..., w - half :].flip(-1).conj())  # (..., 2Hp, Wp/2 + 1)
    both = torch.fft.fft(along_x, dim=-2) * ty
    both = 0.5 * (both[..., :h, :] + both[..., h:, :])  # (..., Hp, Wp/2 + 1)
    return torch.fft.irfft(torch.fft.ifft(both, dim=-2), n=w, dim=-1)


def pixel_averaged_intensity(field_spectrum: torch.Tensor) -> torch.Tensor:
    """Mean of ``|E|²`` over each pixel of the window, (..., Hp, Wp) real, from the field's unshifted spectrum.

    ``field_spectrum``: ``fft2(E)`` on the periodic window (even sizes), E band-limited below the window's
    Nyquist frequency. Exact (to rounding) when the intensity's band is below ``1/dx``.
    """
    return pixel_average_from_fine(fine_field(field_spectrum))
