"""Per-visit steps of the source positions (issue 12, item 4): checked against their definition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from napari_fdt import Optics
from napari_fdt.recon.calibration.calibration import Calibration, RowAdam
from napari_fdt.recon.settings.config import SolverConfig, StageConfig

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
    cal.envelope_stages = frozenset({0})
    cal.set_trainable(1)  # a multi-slice stage: ``multislice_source_step_scale`` (2) times the step and its cap
    step = cal.optimiser.rows.param_groups[0]["lr"]
    assert step == pytest.approx(2.0 * min(lr * max(1.0, n_sources / batch), 0.6 / (4 * 0.65)))
    assert cal.optimiser.rows.param_groups[0]["max_step"] == pytest.approx(2.0 * 0.6 / (4 * 0.65))
    cal.set_trainable(0)  # the envelope stage: scale 1, its own batch size (4)
    assert cal.optimiser.rows.param_groups[0]["lr"] == pytest.approx(min(lr * max(1.0, n_sources / 4), 0.6 / (4 * 0.65)))
    assert cal.optimiser.rows.param_groups[0]["max_step"] == pytest.approx(0.6 / (4 * 0.65))
    assert cal.optimiser.adam.param_groups[-1]["lr"] == cfg.lr_depth_offset_um  # the common offset: its own dense step


def test_dense_mode_keeps_plain_adam_for_the_positions() -> None:
    cfg = SolverConfig(source_step="dense", lr_sources_um=0.02)
    cal = Calibration(np.zeros((8, 3)), cfg, OPTICS, device=torch.device("cpu"), dtype=torch.float32)
    cal.set_trainable(1)
    assert cal.optimiser.rows is None
    assert any(cal.sources is q and g["lr"] == 0.02 for g in cal.optimiser.adam.param_groups for q in g["params"])


def test_matrix_moment_first_step_is_lr_along_the_gradient() -> None:
    """At the first visit ``V = g·gᵀ``: the step is ``lr·(g·gᵀ + δ·|g|²/3·I)^(-1/2)·g = lr·ĝ/√(1 + δ/3)``."""
    p = torch.zeros(3, 3, dtype=torch.float64, requires_grad=True)
    opt = RowAdam([p], lr=0.1, eps=0.0, moment="matrix", damping=0.01)
    g = torch.tensor([[2.0, -1.0, 0.1], [0.0, 0.0, 0.0], [-3.0, 4.0, 0.0]], dtype=torch.float64)
    p.grad = g.clone()
    opt.step()
    norm = g.norm(dim=1, keepdim=True)
    expected = torch.where(norm > 0, -0.1 * g / norm.clamp_min(1e-300) / (1 + 0.01 / 3) ** 0.5, torch.zeros_like(g))
    assert torch.allclose(p.detach(), expected, rtol=1e-10, atol=1e-15)


def _valley(n_steps: int, moment: str) -> float:
    """Distance to the minimum after ``n_steps`` visits of ``½·xᵀHx`` whose soft direction (curvature 1/100 of the
    others) mixes x and depth like a deep source's ray to the field: (0.5, 0, 1)."""
    u = torch.tensor([0.5, 0.0, 1.0], dtype=torch.float64) / 1.25 ** 0.5
    a = torch.tensor([1.0, 0.0, -0.5], dtype=torch.float64) / 1.25 ** 0.5
    r = torch.stack([a, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), u], 1)
    h = r @ torch.diag(torch.tensor([1.0, 1.0, 0.01], dtype=torch.float64)) @ r.T
    p = torch.tensor([[1.0, -0.8, 1.2]], dtype=torch.float64, requires_grad=True)
    opt = RowAdam([p], lr=0.05, moment=moment)
    for _ in range(n_steps):
        p.grad = p.detach() @ h
        opt.step()
    return float(p.detach().norm())


def test_matrix_moment_walks_along_a_coupled_valley() -> None:
    """Full-matrix second moments whiten the coupled direction: 100 visits bring the row within 0.05 of the
    minimum (start 1.75 away), where the isotropic scale, stepping across the valley, is still over 1 away."""
    assert _valley(100, "matrix") < 0.05
    assert _valley(100, "isotropic") > 1.0


def test_steps_longer_than_max_step_are_shortened() -> None:
    p = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    opt = RowAdam([p], lr=1.0, moment="matrix", max_step=0.2)
    p.grad = torch.tensor([[1.0, 2.0, 2.0]], dtype=torch.float64)
    opt.step()
    assert float(p.detach().norm()) == pytest.approx(0.2, rel=1e-12)


@pytest.mark.parametrize("factors, coarse, in_envelope, frozen", [
    ((4, 2, 1), "envelope", False, {0, 1}),
    ((4, 2, 1), "envelope", True, set()),
    ((4, 2, 1), "multislice", False, set()),
    ((4, 2), "envelope", False, set()),  # no multi-slice stage follows: the envelope stages are all there is
])
def test_positions_train_only_in_multislice_stages(factors, coarse, in_envelope, frozen) -> None:
    from napari_fdt.recon.run.solver import position_frozen_stages

    cfg = SolverConfig(stages=[StageConfig(f, 1) for f in factors], calibration_from_stage=0,
                       calibrate_sources_in_envelope_stages=in_envelope)
    assert position_frozen_stages(cfg, coarse) == frozen
    cal = Calibration(np.zeros((4, 3)), cfg, OPTICS, device=torch.device("cpu"), dtype=torch.float32)
    cal.position_frozen_stages = frozenset(frozen)
    for i in range(len(factors)):
        cal.set_trainable(i)
        assert cal.sources.requires_grad == (i not in frozen)
        assert cal.depth_offset_um.requires_grad == (i not in frozen)
        assert cal.log_gain.requires_grad


@pytest.fixture(scope="module")
def deep16():
    """16 noise-free images of a 32², 4-slice letters scene, sources 20 µm deep spread 12 µm off the axis (the
    lateral–depth coupling of issue 12's scene: a source's depth and its shift along the ray to the field move its
    image almost alike)."""
    from napari_fdt import simulate, source_grid
    from napari_fdt.sim.phantoms import text_phantom

    o = Optics(wavelength_um=0.6, n_background=1.33, na=0.65, pixel_size_um=0.33, n_slices=4, slice_spacing_um=1.5,
               image_plane_um=0.0)
    return simulate(text_phantom((32, 32), 4, text="UC", delta_n=0.05), o, source_grid(4, 24.0, 20.0), seed=3,
                    noise=False, brightness_spread=0.0, device="cpu")


def _fixed_volume_fit(sim, start: np.ndarray, source_step: str, iterations: int) -> np.ndarray:
    """Positions fitted by the solver's loss, batches and calibration optimiser with the volume held at the truth."""
    from napari_fdt.recon.problem.losses import total_loss
    from napari_fdt.recon.run.solver import Reconstructor

    cfg = SolverConfig(stages=[StageConfig(1, iterations)], batch_size=4, validation_fraction=0.0, tv_xy_weight=0.0,
                       tv_z_weight=0.0, calibration_from_stage=0, calibrate_source_depth=False, source_step=source_step,
                       lr_sources_um=0.02)
    rec = Reconstructor(sim.acquisition, cfg, device="cpu", initial_sources_um=start)
    stage = rec._build_stage(0)
    dn = torch.as_tensor(sim.ri - sim.acquisition.optics.n_background, dtype=torch.float32)
    rec._init_gains(stage, None)
    rec.calibration.set_trainable(0)
    opt = rec.calibration.optimiser
    for it in range(iterations):
        idx = rec.batches.next(4)
        loss, _ = total_loss(rec._predict_normalised(stage, dn, idx), stage.images[idx], dn, rec.loss_weights,
                             it / iterations, data_range=float(stage.images.max()))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return rec.sources_um()


def test_fixed_volume_fit_returns_to_the_true_positions(deep16) -> None:
    """With the volume at the truth and noise-free images the true positions are the loss's minimum: started 0.5 µm
    off in x, y and depth (0.87 µm in all), whitened per-visit steps bring every source back within 0.1 µm RMS in
    40 visits per source (isotropic per-visit steps: 0.19 µm at 120 iterations, whitened 0.09)."""
    rng = np.random.default_rng(0)
    truth = deep16.sources_um
    start = truth + 0.5 * np.sign(rng.standard_normal(truth.shape))
    fitted = _fixed_volume_fit(deep16, start, "whitened", 160)
    err = fitted - truth
    lateral = float(np.sqrt((err[:, :2] ** 2).sum(1).mean()))
    depth = float(np.sqrt((err[:, 2] ** 2).mean()))
    assert lateral < 0.1 and depth < 0.2, (lateral, depth)


@pytest.mark.parametrize("source_step", ["dense", "whitened"])
def test_an_older_checkpoints_single_adam_state_loads(source_step) -> None:
    """Checkpoints written before the rows' optimiser hold torch's Adam state with the positions as the first group:
    the other groups' moments carry over; the positions' too when they step with that same Adam ("dense")."""
    cfg = SolverConfig(source_step=source_step)
    cal = Calibration(np.zeros((4, 3)), cfg, OPTICS, device=torch.device("cpu"), dtype=torch.float32)
    cal.set_trainable(1)
    params = [cal.sources, cal.log_gain, cal.pixel_scale, cal.spacing_scale, cal.depth_offset_um, cal.na_scale,
              cal.pupil_edge, cal.zernike]
    old = torch.optim.Adam([{"params": [cal.sources]}, {"params": [cal.log_gain]}, {"params": [cal.pixel_scale, cal.spacing_scale]},
                            {"params": [cal.depth_offset_um]}, {"params": [cal.na_scale, cal.pupil_edge]}, {"params": [cal.zernike]}], lr=0.02)
    for p in params:
        p.grad = torch.ones_like(p)
    old.step()
    cal.optimiser.load_state_dict(old.state_dict())
    state = cal.optimiser.state
    assert torch.equal(state[cal.log_gain]["exp_avg"], old.state[cal.log_gain]["exp_avg"])
    assert (cal.sources in state and torch.equal(state[cal.sources]["exp_avg"], old.state[cal.sources]["exp_avg"])) == (source_step == "dense")


def _step_once(cal: Calibration, grad_rows: torch.Tensor) -> None:
    """One optimiser step with ``grad_rows`` (N, 3) as the positions' gradient and 1 as the depth offset's."""
    cal.optimiser.zero_grad(set_to_none=True)
    cal.sources.grad = grad_rows.clone().to(cal.sources.dtype)
    cal.depth_offset_um.grad = torch.ones_like(cal.depth_offset_um)
    cal.optimiser.step()


@pytest.mark.parametrize("restart", [True, False])
def test_a_new_stage_restarts_the_moments_of_the_positions_and_depth_offset(restart) -> None:
    """``restart_source_moments``: at a new stage the rows' moments, visit counts and the offset's Adam state are gone,
    so the next visit is a first Adam step again (length ``lr`` along the new gradient, whatever the old stage's
    gradients were); set_trainable again within the same stage (a restart of the stage) keeps them."""
    cfg = SolverConfig(stages=[StageConfig(2, 1), StageConfig(1, 1)], calibration_from_stage=0, batch_size=4,
                       source_step="whitened", restart_source_moments=restart)
    cal = Calibration(np.zeros((4, 3)), cfg, OPTICS, device=torch.device("cpu"), dtype=torch.float64)
    cal.set_trainable(0)
    for _ in range(5):  # an earlier stage's gradient, large and along x
        _step_once(cal, torch.tensor([[100.0, 0.0, 0.0]] * 4))
    cal.set_trainable(0)
    assert cal.optimiser.state[cal.sources]["visits"].tolist() == [5.0] * 4
    cal.set_trainable(1)
    assert (cal.sources not in cal.optimiser.state and cal.depth_offset_um not in cal.optimiser.state) == restart
    before = cal.sources.detach().clone()
    g = torch.tensor([[0.0, 1e-3, 0.0]] * 4)
    _step_once(cal, g)
    moved = cal.sources.detach() - before
    lr = cal.optimiser.rows.param_groups[0]["lr"]
    if restart:  # a first step: lr along -g (matrix moment: lr·ĝ/√(1 + δ/3))
        assert torch.allclose(moved, -lr * torch.tensor([[0.0, 1.0, 0.0]] * 4, dtype=torch.float64) / (1 + 0.01 / 3) ** 0.5, atol=1e-9)
    else:  # the old stage's momentum along x still steers it, the old gradient scale shrinks the y step
        assert float(moved[:, 0].abs().min()) > 0.5 * lr and float(moved[:, 1].abs().max()) < 0.01 * lr


@pytest.mark.parametrize("factors, coarse, depth_in_envelope, frozen", [
    ((4, 2, 1), "envelope", False, {0, 1}),
    ((4, 2, 1), "envelope", True, set()),
    ((4, 2, 1), "multislice", False, set()),
    ((4, 2), "envelope", False, set()),
])
def test_depths_stay_fixed_in_envelope_stages_while_xy_train(factors, coarse, depth_in_envelope, frozen) -> None:
    """``calibrate_source_depth_in_envelope_stages`` off: in the envelope stages before a multi-slice stage the gradient
    reaches x and y of every source but neither its own depth nor the common offset."""
    from napari_fdt.recon.run.solver import depth_frozen_stages

    cfg = SolverConfig(stages=[StageConfig(f, 1) for f in factors], calibration_from_stage=0,
                       calibrate_source_depth_in_envelope_stages=depth_in_envelope)
    assert depth_frozen_stages(cfg, coarse) == frozen
    cal = Calibration(np.zeros((4, 3)), cfg, OPTICS, device=torch.device("cpu"), dtype=torch.float64)
    cal.depth_frozen_stages = frozenset(frozen)
    weights = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    for i in range(len(factors)):
        cal.set_trainable(i)
        cal.sources.grad = None
        (cal.calibrated_sources() * weights).sum().backward()
        assert torch.equal(cal.sources.grad[:, :2], torch.tensor([[1.0, 2.0]] * 4, dtype=torch.float64))
        assert float(cal.sources.grad[:, 2].abs().sum()) == (0.0 if i in frozen else 12.0)
        assert cal.depth_offset_um.requires_grad == (i not in frozen)


def test_cosine_schedule_shortens_each_visit_as_half_one_plus_cos() -> None:
    """``source_step_schedule = "cosine"``: with a constant gradient (Adam's step then ``lr`` at every visit) the v-th
    visit of the stage (from 0) moves ``lr·½(1 + cos(π·v/V))``, V = iterations·B/N, and nothing from the V-th on."""
    cfg = SolverConfig(stages=[StageConfig(2, 8), StageConfig(1, 8)], calibration_from_stage=0, batch_size=2,
                       source_step="per_visit", source_step_schedule="cosine", restart_source_moments=False,
                       lr_sources_um=0.001)
    cal = Calibration(np.zeros((4, 3)), cfg, OPTICS, device=torch.device("cpu"), dtype=torch.float64)
    cal.envelope_stages = frozenset({0})
    g = torch.tensor([[1.0, 1.0, 1.0]] * 4)
    cal.set_trainable(0)  # the envelope stage: constant steps
    for _ in range(3):
        _step_once(cal, g)
    cal.set_trainable(1)  # V = 8 iterations · 2 / 4 images = 4 visits, counted from this stage's start
    lr = cal.optimiser.rows.param_groups[0]["lr"]
    moves = []
    for _ in range(6):
        before = cal.sources.detach().clone()
        _step_once(cal, g)
        moves.append(float((before - cal.sources.detach())[0, 0]))
    expected = [lr * 0.5 * (1 + np.cos(np.pi * min(v / 4, 1.0))) for v in range(6)]
    assert np.allclose(moves, expected, rtol=1e-6, atol=1e-12)


def test_newton_schulz_inverse_square_root_equals_eigh() -> None:
    """The GPU's sync-free ``A^(-1/2)`` against ``eigh`` on damped second moments like the source step's: a rank-one
    first visit (two equal eigenvalues), random 3x3 ones, and the worst conditioning the damping allows (κ = C/δ)."""
    from napari_fdt.recon.calibration.calibration import inverse_sqrt_spd

    gen = torch.Generator().manual_seed(3)
    g = torch.randn(40, 3, generator=gen, dtype=torch.float64)
    rank_one = g[:, :, None] * g[:, None, :]
    mixed = torch.randn(40, 3, 5, generator=gen, dtype=torch.float64)
    full = mixed @ mixed.transpose(1, 2) * torch.logspace(-6, 6, 40, dtype=torch.float64)[:, None, None]
    for v, delta in ((rank_one, 0.01), (full, 0.01), (rank_one, 0.001)):
        tr = torch.diagonal(v, dim1=-2, dim2=-1).sum(-1)
        a = v + (delta * tr / 3)[:, None, None] * torch.eye(3, dtype=torch.float64)
        lam, q = torch.linalg.eigh(a)
        ref = (q * lam.rsqrt()[:, None, :]) @ q.transpose(1, 2)
        got = inverse_sqrt_spd(a, condition_bound=3 / delta)
        err = ((got - ref).norm(dim=(1, 2)) / ref.norm(dim=(1, 2))).max()
        assert float(err) < 1e-11


@pytest.mark.parametrize("moment", ["isotropic", "matrix"])
def test_masked_step_equals_the_rows_step(moment: str) -> None:
    """The GPU's step over every row with the unvisited masked out gives the visited rows' step of the CPU's form, and
    leaves the other rows and their moments alone: 12 steps, random visits, the step cap and the cosine decay on."""
    gen = torch.Generator().manual_seed(5)
    start = torch.randn(9, 3, generator=gen, dtype=torch.float64)
    opts, params = [], []
    for sync_free in (False, True):
        p = start.clone().requires_grad_(True)
        opt = RowAdam([p], lr=0.05, moment=moment, max_step=0.08)
        opt.param_groups[0]["cosine_visits"] = 6.0
        opt.param_groups[0]["cosine_from"] = torch.arange(9, dtype=torch.float64)[:, None] % 3
        opt.sync_free = sync_free
        opts.append(opt)
        params.append(p)
    for _ in range(12):
        g = torch.randn(9, 3, generator=gen, dtype=torch.float64)
        g[torch.rand(9, generator=gen) < 0.5] = 0.0  # about half the rows not in this batch
        for p, opt in zip(params, opts):
            p.grad = g.clone()
            opt.step()
    assert torch.allclose(params[1].detach(), params[0].detach(), rtol=1e-10, atol=1e-13)
    assert not torch.equal(params[0].detach(), start)
    for key in ("exp_avg", "exp_avg_sq", "visits"):
        assert torch.allclose(opts[1].state[params[1]][key], opts[0].state[params[0]][key], rtol=1e-12, atol=0)
