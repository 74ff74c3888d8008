"""Partial coherence of fluorescence: the emission spectrum and the paper's binary masks.

Two-photon fluorescence is spatially almost coherent at these depths, but its emission band
(20-60 nm FWHM) makes it temporally partially coherent: fringes whose path difference exceeds the
coherence length ``λ²/(n_b·Δλ)`` (4-10 µm) wash out. Two remedies (``docs/physics.md``, "Partial
coherence"):

* **Spectral sum** (:func:`spectral_images`): emission at different wavelengths does not interfere,
  so the image is the incoherent sum ``Σ_k w_k · I(λ_k)`` over a quadrature of the emission spectrum
  (:func:`emission_spectrum`). Exact for a stationary source, differentiable, K× the cost.
* **Masks** (:func:`coherence_masks`): the paper's remedy. The homogeneous-medium image of each
  source (a defocused Airy disc) binarised at a fraction of its maximum; prediction and measurement
  are both multiplied by it before the loss.

Lengths in µm.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from napari_fdt.errors import FDTInputError
from napari_fdt.model.protocol import ImageModel

__all__ = ["FWHM_PER_SIGMA", "MASK_BATCH", "emission_spectrum", "spectral_images", "coherence_masks", "coherence_length_um"]

#: FWHM of a Gaussian over its standard deviation, 2·sqrt(2·ln 2) = 2.3548.
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


def emission_spectrum(center_um: float, fwhm_um: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Wavelengths and weights sampling a Gaussian emission spectrum by Gauss–Hermite quadrature.

    The spectrum is a Gaussian in vacuum wavelength with centre ``center_um`` and full width at half
    maximum ``fwhm_um`` (σ = FWHM/2.3548). The ``n`` nodes are ``center + σ·x_k`` with ``x_k`` the
    probabilists' Hermite nodes (:func:`numpy.polynomial.hermite_e.hermegauss`), and the weights sum to
    1: ``Σ w_k·f(λ_k)`` is the spectral mean of ``f``, exact for polynomials of degree ≤ 2n − 1 (so the
    mean is the centre and, for n ≥ 2, the variance is σ²).

    ``n = 1`` or ``fwhm_um = 0`` give ``([center], [1])``. Returns float64 arrays of length n (or 1).
    """
    center = float(center_um)
    if not (math.isfinite(center) and center > 0):
        raise FDTInputError("wavelength_um", f"must be positive, got {center_um!r}", "give the vacuum emission wavelength in µm")
    fwhm = float(fwhm_um)
    if not (math.isfinite(fwhm) and fwhm >= 0):
        raise FDTInputError("bandwidth_um", f"must be >= 0, got {fwhm_um!r}", "give the emission FWHM in µm, e.g. 0.04, or 0 for a single wavelength")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or int(n) < 1:
        raise FDTInputError("n_wavelengths", f"must be a whole number >= 1, got {n!r}", "use 3-9 wavelengths, e.g. 9")
    n = int(n)
    if n == 1 or fwhm == 0.0:
        return np.array([center]), np.array([1.0])
    nodes, weights = np.polynomial.hermite_e.hermegauss(n)
    sigma = fwhm / FWHM_PER_SIGMA
    wavelengths = center + sigma * nodes
    weights = weights / weights.sum()
    if wavelengths.min() <= 0:
        raise FDTInputError(
            "bandwidth_um",
            f"FWHM {fwhm:g} µm around {center:g} µm puts a quadrature wavelength at {wavelengths.min():.3g} µm (<= 0)",
            "give a bandwidth well below the wavelength, or fewer n_wavelengths",
        )
    return wavelengths, weights


def coherence_length_um(wavelength_um: float, fwhm_um: float, n_background: float) -> float:
    """Coherence length in the medium, ``λ²/(n_b·Δλ)`` µm (``inf`` for Δλ = 0); for reports."""
    if fwhm_um == 0:
        return math.inf
    return float(wavelength_um) ** 2 / (float(n_background) * float(fwhm_um))


def _is_acquisition_wavelength(model: ImageModel, lam) -> bool:
    if isinstance(lam, torch.Tensor):
        if lam.requires_grad:
            return False  # keep the gradient path through the override
        lam = lam.detach().cpu().item()
    return float(lam) == float(model.optics.wavelength_um)


def spectral_images(
    model: ImageModel,
    delta_n: torch.Tensor,
    sources_um: torch.Tensor,
    gain: torch.Tensor | None = None,
    wavelengths_um: Sequence[float] | np.ndarray | torch.Tensor | None = None,
    weights: Sequence[float] | np.ndarray | torch.Tensor | None = None,
    **optics_overrides,
) -> torch.Tensor:
    """Images of partially coherent emission, ``Σ_k w_k · model(delta_n, sources, gain, wavelength_um=λ_k)``.

    ``wavelengths_um`` and ``weights`` (e.g. from :func:`emission_spectrum`) have the same length K ≥ 1;
    None for both is the acquisition's wavelength with weight 1. The weights are used as given (pass
    normalised ones to keep the intensity scale). A wavelength equal to the acquisition's uses the
    model's cached kernels, so one such wavelength with weight 1 gives exactly ``model(...)``.
    Differentiable in ``delta_n``, ``sources_um``, ``gain``, the weights and tensor wavelengths; the
    cost is K forward passes. Further keyword arguments (``pixel_size_um``, ``slice_spacing_um``) go to
    every model call (self-calibration). An empty batch (B = 0) gives a (0, h, w) stack without calling the model.
    """
    if sources_um.shape[0] == 0:  # no image to predict (a batch's share on a rank that owns none of it, or only
        # held-out ones): no model call, since MKL's FFT refuses a batch of zero ("Inconsistent configuration parameters")
        return torch.zeros((0, *model.image_shape), device=delta_n.device, dtype=delta_n.dtype)
    if wavelengths_um is None and weights is None:
        return model(delta_n, sources_um, gain, **optics_overrides)
    if wavelengths_um is None or weights is None:
        raise FDTInputError("weights" if weights is None else "wavelengths_um", "is missing", "give both wavelengths_um and weights, of equal length")
    lams = list(wavelengths_um) if not isinstance(wavelengths_um, torch.Tensor) else list(wavelengths_um.reshape(-1))
    ws = list(weights) if not isinstance(weights, torch.Tensor) else list(weights.reshape(-1))
    if len(lams) == 0 or len(lams) != len(ws):
        raise FDTInputError(
            "n_wavelengths", f"got {len(lams)} wavelengths and {len(ws)} weights", "give as many weights as wavelengths, at least one"
        )
    total = None
    for lam, w in zip(lams, ws):
        if _is_acquisition_wavelength(model, lam):
            img = model(delta_n, sources_um, gain, **optics_overrides)
        else:
            lam = lam if isinstance(lam, torch.Tensor) else float(lam)
            img = model(delta_n, sources_um, gain, wavelength_um=lam, **optics_overrides)
        if isinstance(w, torch.Tensor):
            w = w.to(img.device, img.dtype)
        else:
            w = float(w)
        term = img * w
        total = term if total is None else total + term
    return total


def _gaussian_blur(images: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """Separable Gaussian blur of (B, H, W) images, edges extended (replicate), same shape."""
    radius = max(1, int(math.ceil(4.0 * sigma_px)))
    t = torch.arange(-radius, radius + 1, device=images.device, dtype=images.dtype)
    k = torch.exp(-0.5 * (t / sigma_px) ** 2)
    k = k / k.sum()
    x = images.unsqueeze(1)  # (B, 1, H, W)
    x = F.pad(x, (radius, radius, radius, radius), mode="replicate")
    x = F.conv2d(x, k.reshape(1, 1, 1, -1))
    x = F.conv2d(x, k.reshape(1, 1, -1, 1))
    return x.squeeze(1)


#: Sources imaged together by :func:`coherence_masks` (its memory is that many fields of the model's window, not the stack's).
MASK_BATCH = 16


def coherence_masks(
    model: ImageModel,
    sources_um: torch.Tensor | np.ndarray,
    *,
    threshold: float = 0.5,
    wavelengths_um: Sequence[float] | np.ndarray | torch.Tensor | None = None,
    weights: Sequence[float] | np.ndarray | torch.Tensor | None = None,
    smooth_um: float | None = None,
    batch_size: int = MASK_BATCH,
) -> torch.Tensor:
    """The paper's binary masks, (B, H, W) float 0/1 on the model's device, without gradient.

    Mask i is the homogeneous-medium image (Δn = 0) of source i, through the same pupil and window as
    the model (optionally summed over an emission spectrum), set to 1 where it reaches ``threshold``
    times its own maximum and 0 elsewhere: the defocused Airy disc of the source at the focal plane,
    of radius close to ``h·tan(asin(NA/n_b))`` with ``h = depth + T − image_plane_um`` (the 50 % contour
    lies about 10 % inside it, where the disc's Fresnel edge falls off; ``docs/physics.md``).

    ``smooth_um``: σ of a Gaussian blur applied to each image before binarising. The defocused disc is
    crossed by fringes of period about λ/NA (the pupil's rim wave beating with the direct light) and
    has a spike of up to 2× the disc's level on its axis; binarising the raw image at half its
    maximum then gives broken rings or a dot instead of the disc (at NA 0.5, 28 µm defocus: 5 pieces
    covering 36 % of the disc). None (default) blurs by λ/NA, which removes them; 0 binarises the raw
    image (the literal rule).

    ``batch_size``: sources imaged together (each pass holds that many fields of the model's window; the masks of all
    1521 sources of a full-size stack in one pass took over 24 GB).
    """
    if not (isinstance(threshold, (int, float)) and 0.0 < float(threshold) < 1.0):
        raise FDTInputError("threshold", f"must be in (0, 1), got {threshold!r}", "use e.g. 0.5 (half the maximum)")
    o = model.optics
    sigma_um = o.wavelength_um / o.na if smooth_um is None else float(smooth_um)
    if not (math.isfinite(sigma_um) and sigma_um >= 0):
        raise FDTInputError("smooth_um", f"must be >= 0, got {smooth_um!r}", "use None (λ/NA) or 0 for no blur")
    src = sources_um if isinstance(sources_um, torch.Tensor) else torch.as_tensor(np.asarray(sources_um, dtype=np.float64))
    src = src.detach().to(model.device, model.dtype).reshape(-1, 3)
    h, w = model.image_shape
    sigma_px = sigma_um / model.pixel_size_um
    step = max(1, int(batch_size))
    out = torch.empty((src.shape[0], h, w), device=model.device, dtype=model.dtype)
    with torch.no_grad():
        zero = torch.zeros((o.n_slices, h, w), device=model.device, dtype=model.dtype)
        for start in range(0, src.shape[0], step):  # (model/render.iter_batches imports this module)
            part = slice(start, start + step)
            img = spectral_images(model, zero, src[part], None, wavelengths_um, weights)
            if sigma_px > 0:
                img = _gaussian_blur(img, sigma_px)
            peak = img.amax(dim=(-2, -1), keepdim=True)
            out[part] = (img >= float(threshold) * peak).to(model.dtype)
    return out
