"""Obliquity of the thin phase screen, measured with MultiSliceModel against the exact slab (``benchmarks/obliquity.py``).

A uniform slab filling the window gives every plane-wave component the exact phase
``2π·T·(sqrt((n_b+Δn)²/λ² − f²) − sqrt(n_b²/λ² − f²))``; the screens give ``2π·T·Δn/λ`` whatever the angle and the
slice count. Their ratio minus one is ``1/cos θ − 1 − (Δn/(2·n_b))·sin²θ/cos³θ + (Δn²/(2·n_b²))·sin²θ/cos⁵θ + O(Δn³)``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmarks import obliquity as ob  # the benchmark's measurement
from napari_fdt.errors import FDTInputError


@pytest.mark.parametrize("na", [0.3, 0.66, 0.95])
@pytest.mark.parametrize("n_slices", [1, 4])
def test_screen_phase_ignores_obliquity_as_predicted(na: float, n_slices: int) -> None:
    dn = 0.02
    r = ob.measure_plane_wave(na, n_slices, dn)
    # the model: one phase for every component inside the pupil, 2π·T·Δn/λ, for any slice count
    assert r["spread"] < 1e-9 and r["phi_model"] == pytest.approx(2 * math.pi * ob.THICKNESS * dn / ob.LAM, abs=1e-9)
    # measured error against the exact slab = the analytic expansion in Δn (to third order)
    s2 = r["sin_theta"] ** 2
    cos = math.sqrt(1 - s2)
    x = dn / ob.N_B
    expansion = 1 / cos - 1 - x / 2 * s2 / cos**3 + x * x / 2 * s2 / cos**5
    assert r["error"] == pytest.approx(expansion, abs=5e-5)
    assert r["error"] == pytest.approx(r["exact_formula"], abs=1e-9)
    assert abs(r["error"] - (1 / cos - 1)) < 0.011  # first order alone: within Δn/(2·n_b)·tan²θ/cos θ


def test_point_source_under_a_slab_and_the_per_source_correction() -> None:
    """NA 0.45, the whole defocused disc: the screens miss 1.9 % of the image; per-source 1/cos θ screens leave < 0.2 %."""
    r = ob.measure_image(0.45, 8, 0.02, refit=False)
    assert 0.01 < r["model"] < 0.04, r
    assert r["ray_secant"] < 0.1 * r["model"], r
    assert np.isfinite(r["secant_screen"])


def test_the_model_offers_the_per_source_correction() -> None:
    """MultiSliceModel(obliquity="per_source") equals the per-source screens written out independently in the benchmark."""
    o = ob.optics_for(0.66, 4)
    src = np.array([[1.0, -0.5, ob.DEPTH]])
    model = ob.full_window_model(o, src)
    corrected = ob.MultiSliceModel(o, model.plan, device="cpu", dtype=torch.float64, obliquity="per_source")
    hp, wp = model.plan.padded_shape
    dn = 0.02 * torch.rand((4, hp, wp), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    s = torch.tensor(src)
    a = corrected.camera_field(dn, s)
    b = ob.oblique_camera_field(model, dn, s)
    assert torch.allclose(a, b, rtol=1e-12, atol=1e-14)
    assert not torch.allclose(a, model.camera_field(dn, s), rtol=1e-3)
    with pytest.raises(FDTInputError):
        ob.MultiSliceModel(o, model.plan, device="cpu", obliquity="exact")


def test_obliquity_correction_setting_reaches_the_multislice_stages(monkeypatch) -> None:
    import napari_fdt.recon.run.solver as solver
    from napari_fdt.recon.settings.config import SolverConfig, StageConfig
    from napari_fdt.sim.simulate import simulate, source_grid

    o = ob.Optics(wavelength_um=0.6, n_background=1.33, na=0.5, pixel_size_um=0.4, n_slices=2, slice_spacing_um=2.0)
    sim = simulate(np.zeros((2, 24, 24), np.float32), o, source_grid(2, 4.0, 12.0), device="cpu", seed=0)
    seen = []
    real = solver.build_stage

    def spy(*a, **k):
        stage = real(*a, **k)
        seen.append(getattr(stage.model, "obliquity", None))
        return stage

    monkeypatch.setattr(solver, "build_stage", spy)
    cfg = SolverConfig(stages=[StageConfig(1, 2)], batch_size=2, obliquity_correction=True)
    for _ in solver.Reconstructor(sim.acquisition, cfg, device="cpu").run():
        pass
    assert seen == ["per_source"]
