"""Images of the forward model for many sources, in batches and without autograd (simulation, previews, reports).

Shapes: sources (N, 3) µm (x, y, depth below the volume); images (N, H, W) float32, ``gain · |E|²``.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np
import torch

from napari_fdt.model.coherence import spectral_images
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.oversampled import OversampledModel

__all__ = ["iter_batches", "render_images"]


def iter_batches(n: int, batch_size: int) -> Iterator[slice]:
    """Slices covering ``range(n)`` in chunks of ``batch_size``."""
    for start in range(0, n, batch_size):
        yield slice(start, min(start + batch_size, n))


def render_images(
    model: MultiSliceModel | OversampledModel,
    delta_n: np.ndarray | torch.Tensor,
    sources_um: np.ndarray,
    gain: np.ndarray | None = None,
    *,
    batch_size: int = 16,
    wavelengths_um: np.ndarray | None = None,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Noise-free images ``gain · |E|²`` for every source, (N, H, W) float32, computed in batches without autograd.

    With ``wavelengths_um`` and ``weights`` (e.g. :func:`napari_fdt.model.coherence.emission_spectrum`), each image
    is the spectral sum ``Σ_k w_k · gain · |E(λ_k)|²`` (:func:`napari_fdt.model.coherence.spectral_images`).
    """
    dn = torch.as_tensor(np.asarray(delta_n), dtype=model.dtype, device=model.device)
    src = torch.as_tensor(np.asarray(sources_um, dtype=np.float64), dtype=model.dtype)
    g = None if gain is None else torch.as_tensor(np.asarray(gain, dtype=np.float64), dtype=model.dtype)
    out = np.empty((src.shape[0], *model.plan.image_shape), dtype=np.float32)
    with torch.no_grad():
        dn_pad = model.pad_volume(dn)
        for sl in iter_batches(src.shape[0], batch_size):
            out[sl] = spectral_images(model, dn_pad, src[sl], None if g is None else g[sl], wavelengths_um, weights).cpu().numpy()
    return out
