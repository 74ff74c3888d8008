"""The camera and objective of docs/physics.md §3 against a brute-force reference written from the docs alone.

``independent_reference_optics.py`` holds a hard pupil on a window 5× wider than the plan, writes the Zernike
phase in polar form and averages the intensity over each pixel by Gauss–Legendre quadrature; the model uses the
exact homogeneous field (Hankel transform), Cartesian polynomials and a Fourier-domain box filter.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.optics import Optics
from napari_fdt.sim.phantoms import bead_phantom
from tests import independent_reference_optics as ref  # noqa: E402

GEOMETRIES = {
    "na0.8_hard": dict(optics=dict(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=4,
                                   slice_spacing_um=2.0, image_plane_um=0.0),
                       shape=(40, 40), sources=[[-4.0, 3.0, 25.0], [3.5, -2.0, 27.0]], pupil_edge=0.0,
                       aberrations={"spherical": 0.5, "coma_vertical": 0.2, "astigmatism_vertical": 0.15, "defocus": -0.3}),
    "na0.5_edge0.01_focus_inside": dict(
        optics=dict(wavelength_um=0.6, n_background=1.33, na=0.5, pixel_size_um=0.4, n_slices=3, slice_spacing_um=1.5,
                    image_plane_um=3.0),
        shape=(36, 44), sources=[[2.0, 1.0, 20.0], [-3.0, -2.5, 18.0]], pupil_edge=0.01,
        aberrations={"defocus": 0.4, "coma_horizontal": -0.25, "astigmatism_oblique": 0.2, "spherical": 0.3}),
}


@pytest.mark.parametrize("name", sorted(GEOMETRIES))
def test_pupil_aberrations_and_pixels_match_brute_force_reference(name: str) -> None:
    g = GEOMETRIES[name]
    opt = Optics(**g["optics"])
    h, w = g["shape"]
    src = np.array(g["sources"])
    dn = bead_phantom((h, w), opt.n_slices, opt.pixel_size_um, opt.slice_spacing_um, delta_n=0.03, rng=2)
    plan = plan_for_sources(opt, (h, w), src, warn=False)
    model = MultiSliceModel(opt, plan, device="cpu", dtype=torch.float64, pupil_edge=g["pupil_edge"],
                            aberrations=g["aberrations"], pixel_integration=True)
    # an edge narrower than the window's 0.03 needs the exact homogeneous field
    assert model.exact_free_field == (g["pupil_edge"] < 0.03)
    ours = model(torch.tensor(dn), torch.tensor(src)).numpy()
    theirs = ref.forward_images_optics(g["optics"], opt.n_background + dn, src, np.ones(len(src)),
                                       pupil_edge=g["pupil_edge"], aberrations=g["aberrations"], pixel_integration=True)
    err = [np.linalg.norm(a - b) / np.linalg.norm(b) for a, b in zip(ours, theirs)]
    print(name, "relative image errors", np.round(err, 5))
    assert max(err) < 0.01, err
    # each part matters here: without it the model is far from the reference
    plain = MultiSliceModel(opt, plan, device="cpu", dtype=torch.float64)(torch.tensor(dn), torch.tensor(src)).numpy()
    assert min(np.linalg.norm(a - b) / np.linalg.norm(b) for a, b in zip(plain, theirs)) > 5 * max(err)
