"""The validation split: which images are held out, the error they report, and the best-iterate tracker."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from napari_fdt.errors import FDTWarning
from napari_fdt.recon.assess.validation import MIN_VALIDATION_IMAGES, BestIterate, holdout_indices, per_image_errors, relative_image_error


def _grid(n: int, pitch_um: float = 5.0, depth_um: float = 20.0) -> np.ndarray:
    g = (np.arange(n) - (n - 1) / 2) * pitch_um
    yy, xx = np.meshgrid(g, g, indexing="ij")
    return np.c_[xx.ravel(), yy.ravel(), np.full(n * n, depth_um)]


def test_per_image_errors_are_each_images_relative_error() -> None:
    rng = np.random.default_rng(3)
    measured = torch.from_numpy(rng.uniform(1.0, 2.0, (4, 8, 8)))
    pred = measured * torch.tensor([1.0, 1.1, 0.8, 1.3], dtype=torch.float64)[:, None, None]
    assert per_image_errors(pred, measured) == pytest.approx([0.0, 0.1, 0.2, 0.3], abs=1e-12)
    assert per_image_errors(pred, measured, fit_gain=True) == pytest.approx([0.0] * 4, abs=1e-9)  # a gain per image fits each


@pytest.mark.parametrize("side", [8, 14, 20])
def test_holdout_takes_the_fraction_spread_over_the_field(side: int) -> None:
    src = _grid(side)
    idx = holdout_indices(src, 0.1)
    n = side * side
    assert len(idx) == max(MIN_VALIDATION_IMAGES, round(0.1 * n))
    assert len(np.unique(idx)) == len(idx) and np.all(np.diff(idx) > 0)
    # spread: every quadrant of the field holds some of them, and their centroid is near the field's centre
    xy = src[idx, :2]
    quadrants = {(bool(x > 0), bool(y > 0)) for x, y in xy}
    assert len(quadrants) == 4, xy
    half_span = 0.5 * (side - 1) * 5.0
    assert np.all(np.abs(xy.mean(axis=0)) < 0.35 * half_span), xy.mean(axis=0)
    # no two held-out sources are neighbours on the grid when there is room (they sample the field, not a patch)
    if side >= 14:
        d = np.sqrt(((xy[:, None] - xy[None]) ** 2).sum(-1)) + np.eye(len(xy)) * 1e9
        assert d.min() > 5.0 * 1.01


def test_holdout_is_deterministic_and_ignores_depth() -> None:
    src = _grid(10)
    a = holdout_indices(src, 0.1)
    b = holdout_indices(src * np.array([1.0, 1.0, 3.0]), 0.1)
    assert np.array_equal(a, b)


def test_holdout_off_and_too_few_images() -> None:
    assert holdout_indices(_grid(8), 0.0).size == 0
    with pytest.warns(FDTWarning, match="validation_fraction"):
        assert holdout_indices(_grid(3), 0.1).size == 0  # 9 images cannot spare 3 and keep 75 % to train on
    assert len(holdout_indices(_grid(4), 0.1)) == MIN_VALIDATION_IMAGES  # 16 images: the minimum, not 2
    assert len(holdout_indices(_grid(8), 0.9)) == 16  # never more than a quarter


def test_relative_image_error_against_its_definition() -> None:
    g = torch.Generator().manual_seed(1)
    meas = torch.rand((3, 8, 8), generator=g, dtype=torch.float64) + 0.5
    noise = 0.05 * torch.randn((3, 8, 8), generator=g, dtype=torch.float64)
    pred = meas + noise
    assert relative_image_error(pred, meas) == pytest.approx(float(noise.norm() / meas.norm()), rel=1e-12)
    # a wrong brightness per image is absorbed by the fitted gain, exactly when the shapes agree
    scaled = meas * torch.tensor([0.3, 2.0, 7.0], dtype=torch.float64)[:, None, None]
    assert relative_image_error(scaled, meas) > 0.5
    assert relative_image_error(scaled, meas, fit_gain=True) < 1e-12
    # the mask removes pixels from both sums
    mask = torch.zeros_like(meas)
    mask[:, :4] = 1.0
    bad = meas.clone()
    bad[:, 4:] += 10.0
    assert relative_image_error(bad, meas, mask) == 0.0


def test_best_iterate_keeps_the_minimum_and_detects_a_rise() -> None:
    tracker = BestIterate(tolerance=0.01)
    errors = [0.30, 0.20, 0.15, 0.16, 0.17, 0.18]
    captured = []
    for i, e in enumerate(errors):
        tracker.update(10 * i, e, lambda i=i: captured.append(i) or {"at": i})
    assert tracker.best_error == 0.15 and tracker.best_iteration == 20 and tracker.state == {"at": 2}
    assert captured == [0, 1, 2]  # the state is copied only when a new best is seen
    assert tracker.stalled(3) and not tracker.stalled(4)
    flat = BestIterate(tolerance=0.05)
    for i, e in enumerate([0.2, 0.19, 0.195, 0.196, 0.197]):  # within 5 %: noise, not a rise
        flat.update(i, e, dict)
    assert not flat.stalled(3)


# --------------------------------------------------------------------------------------------
# In the solver
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def scene16():
    """A 32×32, 4-slice letters scene with 16 noisy images: 3 can be held out (a few seconds to reconstruct)."""
    from benchmarks.scenes import tiny_scene

    return tiny_scene(grid=4, seed=2)


def _config(**kw):
    from napari_fdt.recon.settings.config import SolverConfig, StageConfig

    # Fixed TV weights: with "auto" the held-out images choose the weights (test_regularisation.py), which is their use
    base = dict(stages=[StageConfig(2, 6), StageConfig(1, 8)], batch_size=4, snapshot_every=2, validation_fraction=0.2,
                tv_xy_weight=0.0, tv_z_weight=0.0, final_stage_min_passes=0)  # the stages as given
    base.update(kw)
    return SolverConfig(**base)


def test_held_out_images_never_reach_the_volume_and_their_error_is_reported(scene16) -> None:
    """Held-out images are drawn like the others, but only their own position and gain learn from them: with
    their measurements replaced (each flipped: same mean and maximum, other content) the volume is bit-identical."""
    from napari_fdt.data.acquisition import Acquisition
    from napari_fdt.recon.run.solver import Reconstructor

    acq = scene16.acquisition
    # the model parts fixed: the held-out images choose them (by design), and a part kept changes the volume
    rec = Reconstructor(acq, _config(early_stopping="off", **PARTS_OFF), device="cpu")
    held = rec.validation_indices
    assert len(held) == 3
    snaps = list(rec.run())
    altered_images = acq.images.copy()
    altered_images[held] = altered_images[held][:, ::-1, ::-1]
    altered = Acquisition(altered_images, acq.optics, acq.sources_um, extra=acq.extra)  # same camera model (pixel_integration auto)
    other = Reconstructor(altered, _config(early_stopping="off", **PARTS_OFF), device="cpu")
    assert np.array_equal(other.validation_indices, held)
    list(other.run())
    assert np.array_equal(rec.delta_n_full(), other.delta_n_full())
    assert rec.calibration.summary() == other.calibration.summary()  # the shared calibration did not learn from them
    train = np.setdiff1d(np.arange(acq.n_images), held)
    assert np.array_equal(rec.sources_um()[train], other.sources_um()[train])
    assert not np.allclose(rec.sources_um()[held], other.sources_um()[held])  # their own rows did
    assert all(s.validation_error is not None and np.isfinite(s.validation_error) for s in snaps)
    assert all(s.train_error is not None for s in snaps)
    # the final stage's validation error is the held-out images' relative error, predicted independently through
    # the public predict() with their gains fitted here
    pred = rec.predict(held).astype(np.float64)
    meas = acq.images_float32()[held].astype(np.float64)
    g = (pred * meas).sum(axis=(1, 2)) / (pred * pred).sum(axis=(1, 2))
    expected = np.sqrt(((g[:, None, None] * pred - meas) ** 2).sum() / (meas**2).sum())
    record = rec.stages[-1].to_dict()
    assert record["validation_error"] == pytest.approx(expected, rel=1e-3)
    assert snaps[-1].validation_error == record["validation_error"]
    assert any(h.get("validation_error") is not None for h in rec.history)


def test_no_split_leaves_the_run_as_before(scene16) -> None:
    from napari_fdt.recon.run.solver import Reconstructor

    runs = []
    for frac in (0.0, 0.0):
        rec = Reconstructor(scene16.acquisition, _config(validation_fraction=frac), device="cpu")
        snaps = list(rec.run())
        assert all(s.validation_error is None for s in snaps) and rec.validation_indices.size == 0
        runs.append(rec.delta_n_full())
    assert np.array_equal(runs[0], runs[1])


#: Every optional model part fixed off (tests of the early-stopping mechanics with a scripted validation signal).
PARTS_OFF = dict(calibrate_pupil="false", calibrate_aberrations="false", obliquity_correction="false", coherence="none",
                 sub_slices=1, field_oversampling=1)


def test_stop_ends_a_stage_on_a_rise_and_keeps_its_best_iterate(scene16, monkeypatch) -> None:
    """A scripted validation signal: the stage's start (iteration 0) worst, best at the 2nd snapshot, then rising;
    "stop" with patience 2 ends the stage two snapshots later and returns to the state captured at the best one."""
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import StageConfig

    # the optional model parts fixed: their choice at the stage's end could run the stage again (docs/solver.md)
    cfg = _config(stages=[StageConfig(1, 20)], early_stopping="stop", early_stopping_patience=2, snapshot_every=2, **PARTS_OFF)
    rec = Reconstructor(scene16.acquisition, cfg, device="cpu")
    signal = iter([0.95, 0.5, 0.3, 0.4, 0.45, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2])
    monkeypatch.setattr(rec, "validation_error", lambda stage, mask=None: next(signal))
    states = {}
    capture = rec._capture
    monkeypatch.setattr(rec, "_capture", lambda: states.setdefault(len(states), capture()))
    snaps = list(rec.run())
    record = rec.stages[-1]
    assert record.stopped_at == 8  # snapshots at 2, 4 (best), 6, 8: two above the best
    assert record.best_iteration == 4 and record.validation_error == 0.3
    best_state = states[2]  # captured at iterations 0, 2 and 4
    assert torch.equal(rec.volume.x.detach(), best_state["x"])
    assert snaps[-1].stage_complete and snaps[-1].validation_error == 0.3
    assert snaps[-1].global_iteration == 20  # progress counts the skipped iterations


def test_a_stage_that_only_worsens_the_held_out_images_ends_where_it_began(scene16, monkeypatch) -> None:
    """The stage's start is an iterate too: with the held-out error lowest at iteration 0, "best" returns to the
    starting volume (for stage 0: the empty volume, never one that explains the held-out images worse)."""
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import StageConfig

    rec = Reconstructor(scene16.acquisition, _config(stages=[StageConfig(1, 6)], snapshot_every=2, **PARTS_OFF), device="cpu")
    signal = iter([0.1, 0.2, 0.3, 0.4])
    monkeypatch.setattr(rec, "validation_error", lambda stage, mask=None: next(signal))
    snaps = list(rec.run())
    record = rec.stages[-1]
    assert record.best_iteration == 0 and record.validation_error == 0.1 and snaps[-1].validation_error == 0.1
    start = float(rec.volume.delta_n().max())
    assert start == pytest.approx(1e-3 * rec.config.delta_n_max, rel=1e-3)  # the initial floor: nothing was kept


# --------------------------------------------------------------------------------------------
# The error curve of the reconstruction widget (Qt-free part)
# --------------------------------------------------------------------------------------------

def test_error_curve_maps_iterations_and_log_errors_to_pixels() -> None:
    from types import SimpleNamespace

    from napari_fdt.napari.curve import ErrorCurve

    curve = ErrorCurve(margin_px=0)
    curve.reset(100)
    for it, train, val in [(10, 0.1, None), (50, 0.01, 0.02), (100, 0.001, 0.04), (100, float("nan"), None)]:
        curve.add(SimpleNamespace(global_iteration=it, train_error=train, validation_error=val))
    assert len(curve.train) == 3 and len(curve.validation) == 2  # None and NaN skipped
    assert curve.error_range() == (0.001, 0.1)
    lines = curve.polylines(200, 100)
    # x: iteration / total of the width; y: log10 position from the top (0.1 at the top, 0.001 at the bottom)
    assert lines["train"] == [(20.0, 0.0), (100.0, pytest.approx(50.0)), (200.0, 100.0)]
    x, y = lines["validation"][0]
    assert x == 100.0 and y == pytest.approx(100 * (1 - np.log10(0.02 / 0.001) / 2))
    assert curve.caption() == "train 0.001, validation 0.04 (best 0.02 at 50)"
    # a stage run again from its start (iteration 60 after 100): its points replace those from 60 on
    for it in (60, 80):
        curve.add(SimpleNamespace(global_iteration=it, train_error=0.05, validation_error=0.03))
    assert [i for i, _ in curve.train] == [10, 50, 60, 80] and [i for i, _ in curve.validation] == [50, 60, 80]
    narrow = ErrorCurve()
    narrow.add(SimpleNamespace(global_iteration=1, train_error=0.5, validation_error=0.6))
    lo, hi = narrow.error_range()
    assert hi / lo == pytest.approx(10.0) and lo < 0.5 and hi > 0.6  # widened to a decade around the values
