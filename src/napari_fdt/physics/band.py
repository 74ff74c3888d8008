"""The band of the volume's spatial frequencies the images can carry (first-order scattering), lateral and axial.

A source's spherical wave crosses the volume at angles up to ``θ_ill`` to the optical axis (the steepest ray from a
source to the field's edge at the volume's bottom face, :func:`illumination_angle_rad`); the objective collects
scattered light up to ``θ_det`` (``sin θ_det = NA / n_b``). A weak object's spatial frequency ``K = k_out − k_in``
(``|k| = n_b / λ``, the first Born approximation, docs/physics.md) then reaches the camera only inside

* laterally, ``|K_xy| ≤ (NA + n_b sin θ_ill) / λ``;
* axially, ``|K_z| ≤ (n_b / λ)(1 − cos max(θ_ill, θ_det))`` (one wave along the axis, the other at the largest angle:
  with sources below the field, ``θ_det`` alone gives the depth of field, :attr:`Optics.depth_of_field_um`).

Finer structure than ``1 / K`` (µm) leaves no first-order trace in any image: what a reconstruction shows there comes
from the regulariser and the grid, not the data. These are bounds of the band's extent; inside it the coverage has gaps
(the missing cone) that the bound does not describe. numpy only.
"""

from __future__ import annotations

import math

import numpy as np

from napari_fdt.physics.optics import Optics

__all__ = ["illumination_angle_rad", "band_limit_per_um"]


def illumination_angle_rad(optics: Optics, image_shape: tuple[int, int], sources_um: np.ndarray) -> float:
    """The largest angle (rad) to the optical axis of a straight ray from a source (``sources_um`` (N, 3): x, y from
    the image centre, depth below the volume's bottom face, µm) to a corner of the field (``image_shape`` (H, W) pixels of
    ``optics.pixel_size_um``) on the bottom face."""
    src = np.asarray(sources_um, dtype=np.float64).reshape(-1, 3)
    h, w = image_shape
    half_x, half_y = 0.5 * w * optics.pixel_size_um, 0.5 * h * optics.pixel_size_um
    corners = np.array([[sx * half_x, sy * half_y] for sx in (-1, 1) for sy in (-1, 1)])
    r = np.hypot(*(src[:, None, :2] - corners[None]).transpose(2, 0, 1)).max(axis=1)  # (N,) farthest corner
    depth = np.maximum(src[:, 2], 1e-9)
    return float(np.arctan2(r, depth).max())


def band_limit_per_um(optics: Optics, image_shape: tuple[int, int], sources_um: np.ndarray) -> dict[str, float]:
    """``{"lateral": |K_xy| max, "axial": |K_z| max}`` in cycles/µm (module docstring)."""
    theta_ill = illumination_angle_rad(optics, image_shape, sources_um)
    theta_det = math.asin(optics.na / optics.n_background)
    k = optics.wavenumber_per_um
    return {"lateral": (optics.na + optics.n_background * math.sin(theta_ill)) / optics.wavelength_um,
            "axial": k * (1.0 - math.cos(max(theta_ill, theta_det)))}
