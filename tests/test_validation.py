"""The validation split: which images are held out, the error they report, and the best-iterate tracker."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from napari_fdt.errors import FDTWarning
from napari_fdt.recon.validation import MIN_VALIDATION_IMAGES, BestIterate, holdout_indices, relative_image_error


def _grid(n: int, pitch_um: float = 5.0, depth_um: float = 20.0) -> np.ndarray:
    g = (np.arange(n) - (n - 1) / 2) * pitch_um
    yy, xx = np.meshgrid(g, g, indexing="ij")
    return np.c_[xx.ravel(), yy.ravel(), np.full(n * n, depth_um)]


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
