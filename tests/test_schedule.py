"""The RI step's fall along the finest stage (``lr_ri_final_ratio``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from napari_fdt.recon.config import SolverConfig, StageConfig
from napari_fdt.recon.schedule import final_step_scale
from napari_fdt.recon.solver import Reconstructor


def test_final_step_scale_is_a_half_cosine_from_one_to_the_ratio() -> None:
    n, r = 101, 0.1
    s = [final_step_scale(i, n, r) for i in range(1, n + 1)]
    assert s[0] == pytest.approx(1.0) and s[-1] == pytest.approx(r)
    assert s[50] == pytest.approx(r + (1 - r) * 0.5)  # half way: half way down
    assert s[25] == pytest.approx(r + (1 - r) * 0.5 * (1 + math.cos(math.pi / 4)))
    assert all(a >= b for a, b in zip(s, s[1:]))
    assert final_step_scale(7, 10, 1.0) == 1.0 and final_step_scale(1, 1, 0.1) == 1.0


def _last_moves(acq, ratio: float) -> tuple[float, float]:
    """Δn change over the finest stage's last iteration and over its first, with the step falling to ``ratio``."""
    cfg = SolverConfig(stages=[StageConfig(2, 4), StageConfig(1, 12)], batch_size=8, snapshot_every=1, validation_fraction=0.0,
                       tv_xy_weight=0.0, tv_z_weight=0.0, coherence="none", pixel_integration="false",
                       calibrate_aberrations="false", calibrate_pupil="false", obliquity_correction="false",
                       lr_ri_final_ratio=ratio)
    rec = Reconstructor(acq, cfg, device="cpu")
    finest = [s.delta_n.copy() for s in rec.run() if s.stage == 1]
    return float(np.abs(finest[-1] - finest[-2]).max()), float(np.abs(finest[1] - finest[0]).max())


def test_the_finest_stage_settles_with_a_falling_step() -> None:
    from napari_fdt import Optics, simulate, source_grid
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=2,
               slice_spacing_um=2.0, image_plane_um=0.0)
    acq = simulate(text_phantom((24, 24), 2, text="U", delta_n=0.04), o, source_grid(4, 6.0, 12.0), seed=1,
                   device="cpu", photons=3000.0).acquisition
    const_last, const_first = _last_moves(acq, 1.0)
    fall_last, fall_first = _last_moves(acq, 1e-4)
    # the finest stage's second step is the same but for the cosine's first fall (same state, gradient and moments:
    # Adam's step is the learning rate times their ratio; Δn follows through the activation, nearly linear over one
    # step), the last one 10⁴ times shorter
    assert fall_first == pytest.approx(const_first * final_step_scale(2, 12, 1e-4), rel=1e-2)
    assert fall_last < 1e-2 * const_last
