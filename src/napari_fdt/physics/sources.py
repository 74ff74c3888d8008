"""Band-limited point sources built from their angular spectrum (Weyl expansion).

A fluorophore at lateral position (x_s, y_s) and depth d below the volume's bottom face emits,
in the background medium, ``U = d · exp(i·k·R) / R`` (normalised to unit intensity on its axis at
the bottom face; R the distance to the source, k = 2π·n_b/λ). Its lateral spectrum at height z above
the source is (Weyl)::

    Û(f) = i · d · exp(i·2π·qz·z) · exp(−i·2π·(fx·x_s + fy·y_s)) / qz

(continuous Fourier transform, cycles/µm). We multiply it by a raised-cosine band limit
``B(|f|)`` (1 up to the pupil edge, 0 beyond ``f_hi``) and sample it on the window's FFT grid. The
construction is differentiable in (x_s, y_s, d); the carrier ``exp(i·2π·(n_b/λ)·z)`` is factored out.
"""

from __future__ import annotations

import math

import torch

from napari_fdt.physics.propagation import axial_frequency_offset, raised_cosine

__all__ = ["band_limit", "point_source_spectrum", "spectrum_terms", "centering_sign"]


#: The source's band limit B(|f|): the same raised cosine as the pupil's soft edge.
band_limit = raised_cosine


def centering_sign(padded_shape: tuple[int, int], *, device=None, dtype=torch.float32) -> torch.Tensor:
    """``exp(−i·2π·f·c)`` for the window origin c = (Hp/2, Wp/2) pixels: exactly (−1)^(m+n) for even sizes.

    It moves the field's origin from FFT index 0 to the window's centre pixel, shape (Hp, Wp), real.
    """
    hp, wp = padded_shape
    if hp % 2 or wp % 2:
        raise ValueError("the padded window must have even sizes")
    sy = 1.0 - 2.0 * (torch.arange(hp, device=device) % 2).to(dtype)
    sx = 1.0 - 2.0 * (torch.arange(wp, device=device) % 2).to(dtype)
    return sy.reshape(hp, 1) * sx.reshape(1, wp)


def spectrum_terms(
    fy: torch.Tensor,
    fx: torch.Tensor,
    *,
    n_background: float | torch.Tensor,
    wavelength_um: float | torch.Tensor,
    pixel_size_um: float | torch.Tensor,
    window: torch.Tensor,
    centering: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The sources' spectrum's factors that do not depend on the sources, each (Hp, Wp) real: the axial frequency
    offset ``qz − n_b/λ`` (cycles/µm) and the amplitude per µm of depth ``B(|f|)·centering / (qz·dx²)``.

    A model whose optics are fixed computes them once (:meth:`~napari_fdt.model.forward.MultiSliceModel.source_spectrum`);
    on a GPU every elementwise operation is a kernel launch, and an iteration is bound by those.
    """
    f2 = fy * fy + fx * fx
    offset, propagating = axial_frequency_offset(f2, n_background, wavelength_um)
    k = n_background / wavelength_um
    qz = torch.where(propagating, offset + k, torch.ones_like(offset))
    return offset, window * centering / (qz * pixel_size_um**2)


def point_source_spectrum(
    fy: torch.Tensor,
    fx: torch.Tensor,
    sources_um: torch.Tensor,
    height_offset_um: float | torch.Tensor,
    *,
    n_background: float | torch.Tensor,
    wavelength_um: float | torch.Tensor,
    pixel_size_um: float | torch.Tensor,
    window: torch.Tensor,
    centering: torch.Tensor,
    terms: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Discrete spectrum of a batch of point sources at the plane ``height_offset_um`` above the bottom face.

    Parameters
    ----------
    fy, fx: frequencies of the window, cycles/µm, shapes (Hp, 1), (1, Wp).
    sources_um: (B, 3) tensor of (x, y, depth) in µm; x, y from the image centre, depth > 0 below the
        volume's bottom face. Gradients flow to it.
    height_offset_um: distance of the output plane above the bottom face (the slab's first screen
        sits at half a slice).
    window: band limit ``B(|f|)``, (Hp, Wp) real.
    centering: :func:`centering_sign`, (Hp, Wp) real.
    terms: :func:`spectrum_terms` of the same arguments, made before (None: made here); the result is the same.

    Returns
    -------
    (B, Hp, Wp) complex spectrum ``S`` such that ``torch.fft.ifft2(S)`` is the field envelope on the
    window, pixel (i, j) at ``y = (i − Hp/2)·dx``, ``x = (j − Wp/2)·dx``.
    """
    x = sources_um[:, 0].reshape(-1, 1, 1)
    y = sources_um[:, 1].reshape(-1, 1, 1)
    depth = sources_um[:, 2].reshape(-1, 1, 1)
    if terms is None:
        terms = spectrum_terms(fy, fx, n_background=n_background, wavelength_um=wavelength_um,
                               pixel_size_um=pixel_size_um, window=window, centering=centering)
    offset, amplitude_per_um = terms
    # Signed real amplitude times a unit phasor, assembled from real parts (torch.polar's backward
    # assumes a non-negative modulus, and the centering sign is negative on half the grid).
    amplitude = amplitude_per_um * depth
    phase = (2.0 * math.pi) * (offset * (depth + height_offset_um) - fx * x - fy * y) + 0.5 * math.pi  # the factor i
    return torch.complex(amplitude * torch.cos(phase), amplitude * torch.sin(phase))
