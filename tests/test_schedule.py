"""The RI step's fall along the finest stage (``lr_ri_final_ratio``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from napari_fdt.recon.run.solver import Reconstructor
from napari_fdt.recon.settings.config import SolverConfig, StageConfig
from napari_fdt.recon.settings.schedule import final_step_scale


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
                       lr_ri_final_ratio=ratio, final_stage_min_passes=0)
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


# -- the finest stage's length in passes over the images (``final_stage_min_passes``) ------------------------------
def test_the_finest_stage_is_lengthened_to_the_passes_asked() -> None:
    from napari_fdt.recon.settings.config import resolve_stage_lengths

    cfg = SolverConfig(stages=[StageConfig(4, 100), StageConfig(2, 100), StageConfig(1, 160)], batch_size=16,
                       final_stage_min_passes=24)
    # 196 images in batches of 16: 160 iterations are 13.1 passes; 24 passes need ceil(24·196/16) = 294
    long = resolve_stage_lengths(cfg, 196)
    assert [s.iterations for s in long.stages] == [100, 100, 294]
    assert 294 * 16 / 196 >= 24 > 293 * 16 / 196
    # 64 images: 160 iterations are already 40 passes; nothing changes (the same object: runs stay bit-identical)
    assert resolve_stage_lengths(cfg, 64) is cfg
    # idempotent: a report's config (already lengthened) read back is not lengthened again
    assert resolve_stage_lengths(long, 196) is long
    # 0 keeps the stages as given; a batch larger than the acquisition counts as the whole acquisition
    assert resolve_stage_lengths(SolverConfig(**{**cfg.to_dict(), "final_stage_min_passes": 0}), 196).stages[-1].iterations == 160
    few = SolverConfig(stages=[StageConfig(1, 10)], batch_size=32, final_stage_min_passes=24)
    assert resolve_stage_lengths(few, 8).stages[-1].iterations == 24
    # a stage's own batch size is the one that counts
    own = SolverConfig(stages=[StageConfig(2, 10), StageConfig(1, 10, batch_size=4)], batch_size=16, final_stage_min_passes=2)
    assert [s.iterations for s in resolve_stage_lengths(own, 20).stages] == [10, 10]
    assert [s.iterations for s in resolve_stage_lengths(own, 30).stages] == [10, 15]


def test_the_solver_runs_and_reports_the_lengthened_stage() -> None:
    from napari_fdt import Optics, simulate, source_grid
    from napari_fdt.recon.run.report import stage_lengths
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=2,
               slice_spacing_um=2.0, image_plane_um=0.0)
    acq = simulate(text_phantom((24, 24), 2, text="U", delta_n=0.04), o, source_grid(4, 6.0, 12.0), seed=1,
                   device="cpu", photons=3000.0).acquisition
    cfg = SolverConfig(stages=[StageConfig(2, 2), StageConfig(1, 3)], batch_size=8, snapshot_every=100, validation_fraction=0.0,
                       tv_xy_weight=0.0, tv_z_weight=0.0, coherence="none", pixel_integration="false",
                       calibrate_aberrations="false", calibrate_pupil="false", obliquity_correction="false",
                       final_stage_min_passes=2.5)
    rec = Reconstructor(acq, cfg, device="cpu")
    finest = [s.iteration for s in rec.run() if s.stage == 1]
    # 16 images in batches of 8: 2.5 passes need 5 iterations (3 asked); the coarse stage keeps its 2
    assert finest[-1] == 5 and rec.config.total_iterations == 7 and rec.stages[-1].iterations == 5
    lengths = stage_lengths(rec)
    assert lengths["requested_iterations"] == [2, 3] and lengths["iterations"] == [2, 5]
    assert lengths["passes"] == pytest.approx([1.0, 2.5])
