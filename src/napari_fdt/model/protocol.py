"""The interface every forward model offers to the solver, the stages, the masks and the spectral sum.

:class:`~napari_fdt.model.forward.MultiSliceModel` (full window, exact to the thin-screen model) and
:class:`~napari_fdt.model.envelope.EnvelopeModel` (coarse stages) both implement :class:`ImageModel`.
Lengths in µm; images are ``gain · |E|²`` (dimensionless model units, per source).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch

from napari_fdt.physics.optics import Optics

__all__ = ["ImageModel"]


@runtime_checkable
class ImageModel(Protocol):
    """What :mod:`napari_fdt.recon.problem.stages`, :mod:`napari_fdt.recon.run.solver` and :mod:`napari_fdt.model.coherence` use of a model.

    Attributes: ``optics`` (the acquisition's optics: wavelength, n_b, NA, slices), ``device`` and ``dtype``
    (the real dtype of images and volumes, float32 or float64).
    """

    optics: Optics
    device: torch.device
    dtype: torch.dtype

    @property
    def image_shape(self) -> tuple[int, int]:
        """(h, w) of the images the model returns, and of the contrast volume it takes (its image grid)."""
        ...

    @property
    def pixel_size_um(self) -> float:
        """Pixel of the image grid, µm."""
        ...

    def __call__(
        self,
        delta_n: torch.Tensor,
        sources_um: torch.Tensor,
        gain: torch.Tensor | None = None,
        *,
        slice_spacing_um: float | torch.Tensor | None = None,
        wavelength_um: float | torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Images (B, h, w) real, differentiable in every tensor argument.

        ``delta_n``: contrast n − n_b, (n_slices, h, w) on the image grid; ``sources_um``: (B, 3) positions
        [x, y, depth below the volume] in the model's coordinates; ``gain``: (B,) or None (1).
        ``slice_spacing_um`` and ``wavelength_um`` override the optics' values (self-calibration and the
        spectral sum; None: the optics' value). :class:`~napari_fdt.model.forward.MultiSliceModel` also
        takes ``pixel_size_um``.
        """
        ...
