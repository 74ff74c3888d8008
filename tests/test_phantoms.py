"""The fibre phantom (the thick-slab scene of elongated objects): fibres are where and how thick the recipe says."""

from __future__ import annotations

import numpy as np

from napari_fdt.sim.phantoms import fibre_phantom


def test_fibres_are_capsules_of_the_given_radius_crossing_slices_of_a_thick_slab() -> None:
    vol = fibre_phantom((64, 64), 8, 0.5, 3.0, n_fibres=1, radius_um=(1.0, 1.0), length_um=(12.0, 12.0),
                        max_tilt_deg=30.0, delta_n=0.03, rng=3)
    assert vol.dtype == np.float32 and vol.shape == (8, 64, 64)
    assert 0.6 * 0.03 - 1e-6 <= vol.max() <= 0.03 + 1e-6 and vol.min() == 0.0
    inside = vol > 0.5 * vol.max()
    # the capsule's volume: π r² L + 4/3 π r³ (µm³) against the voxels inside it (0.5 × 0.5 × 3 µm each)
    expected = np.pi * 12.0 + 4.0 / 3.0 * np.pi
    assert abs(inside.sum() * 0.5 * 0.5 * 3.0 - expected) < 0.35 * expected
    many = fibre_phantom((64, 64), 8, 0.5, 3.0, rng=0)
    assert (many > 0.005).any(axis=(1, 2)).sum() >= 6  # tilted fibres reach most slices of the slab
    assert np.array_equal(many, fibre_phantom((64, 64), 8, 0.5, 3.0, rng=0))  # seeded
