"""Per-visit steps of the source positions (issue 12, item 4): checked against their definition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from napari_fdt import Optics
from napari_fdt.recon.calibration import Calibration, RowAdam
from napari_fdt.recon.config import SolverConfig, StageConfig

OPTICS = Optics(wavelength_um=0.6, n_background=1.33, na=0.65, pixel_size_um=0.33, n_slices=4,
                slice_spacing_um=1.5, image_plane_um=0.0)


def test_a_visit_moves_only_the_visited_rows_by_lr_along_the_gradient() -> None:
    """First step of Adam (bias-corrected): ``lr · g / rms(g)`` per visited row, the rms over the row's columns."""
    p = torch.zeros(5, 3, dtype=torch.float64, requires_grad=True)
    opt = RowAdam([p], lr=0.1, eps=0.0)
    g = torch.tensor([[0.0, 0.0, 0.0], [2.0, -1.0, 0.1], [0.0, 0.0, 0.0], [-3.0, 4.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    p.grad = g.clone()
    opt.step()
    rms = g.square().mean(dim=1, keepdim=True).sqrt()
    expected = torch.where(rms > 0, -0.1 * g / rms.clamp_min(1e-300), torch.zeros_like(g))
    assert torch.allclose(p.detach(), expected, rtol=1e-12, atol=0)
    assert opt.state[p]["visits"].tolist() == [0, 1, 0, 1, 0]


def test_unvisited_rows_keep_their_value_and_moments() -> None:
    """Between visits a row neither moves nor decays its moments (dense Adam would move it on stale momentum)."""
    p = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    opt = RowAdam([p], lr=0.05)
    p.grad = torch.tensor([[1.0, 0.5, 0.2], [1.0, 0.5, 0.2]], dtype=torch.float64)
    opt.step()
    before = (p.detach()[0].clone(), opt.state[p]["exp_avg"][0].clone(), opt.state[p]["exp_avg_sq"][0].clone())
    for _ in range(7):
        p.grad = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.5, 0.2]], dtype=torch.float64)
        opt.step()
    assert torch.equal(p.detach()[0], before[0])
    assert torch.equal(opt.state[p]["exp_avg"][0], before[1]) and torch.equal(opt.state[p]["exp_avg_sq"][0], before[2])
    assert opt.state[p]["visits"].tolist() == [1, 8]
    # a constant gradient: every visit moves the row by lr along -g/rms(g), bias-corrected
    g = torch.tensor([1.0, 0.5, 0.2], dtype=torch.float64)
    assert torch.allclose(p.detach()[1], -8 * 0.05 * g / g.square().mean().sqrt(), rtol=1e-6)


@pytest.mark.parametrize("n_sources, batch, lr", [(196, 16, 0.01), (64, 16, 0.01), (1521, 16, 0.01), (10, 32, 0.02)])
def test_step_per_visit_is_lr_times_visit_interval_capped_at_a_quarter_resolution(n_sources, batch, lr) -> None:
    """``min(lr_sources_um · N/B, λ/(4·NA))``, with N/B at least 1; the stage's own batch size counts."""
    cfg = SolverConfig(stages=[StageConfig(2, 1), StageConfig(1, 1, batch_size=batch)], batch_size=4, lr_sources_um=lr,
                       source_step="per_visit")
    cal = Calibration(np.zeros((n_sources, 3)), cfg, OPTICS, device=torch.device("cpu"), dtype=torch.float32)
    cal.set_trainable(1)
    step = cal.optimiser.rows.param_groups[0]["lr"]
    assert step == pytest.approx(min(lr * max(1.0, n_sources / batch), 0.6 / (4 * 0.65)))
    assert cal.optimiser.adam.param_groups[-1]["lr"] == cfg.lr_depth_offset_um  # the common offset: its own dense step


def test_dense_mode_keeps_plain_adam_for_the_positions() -> None:
    cfg = SolverConfig(source_step="dense", lr_sources_um=0.02)
    cal = Calibration(np.zeros((8, 3)), cfg, OPTICS, device=torch.device("cpu"), dtype=torch.float32)
    cal.set_trainable(1)
    assert cal.optimiser.rows is None
    assert any(cal.sources is q and g["lr"] == 0.02 for g in cal.optimiser.adam.param_groups for q in g["params"])
