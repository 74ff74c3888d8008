"""Fixtures shared by several test modules."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def scene16():
    """A 32×32, 4-slice letters scene with 16 noisy images: 3 can be held out (tests of the TV choice and its pilot)."""
    from napari_fdt import Optics, simulate, source_grid
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=4,
               slice_spacing_um=2.0, image_plane_um=0.0)
    return simulate(text_phantom((32, 32), 4, text="UC", delta_n=0.05), o, source_grid(4, 8.0, 15.0), seed=2, device="cpu")
