"""Loss terms and metrics against independent references (numpy formulas, scikit-image's SSIM)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import napari_fdt.recon.problem.losses as losses
from napari_fdt.errors import FDTInputError
from napari_fdt.recon.assess.metrics import (
    image_metrics,
    paper_normalised_metrics,
    psnr,
    relative_delta_n_error,
    ri_metrics,
    rmse,
    volume_ssim,
)
from napari_fdt.recon.problem.losses import (
    LossWeights,
    as_floats,
    l1_l2_weights,
    l1_loss,
    l2_loss,
    ssim,
    ssim_loss,
    total_loss,
    tv_xy,
    tv_z,
)

skmetrics = pytest.importorskip("skimage.metrics")
ndimage = pytest.importorskip("scipy.ndimage")


def _sk_ssim(x: np.ndarray, y: np.ndarray, data_range: float) -> float:
    return float(
        skmetrics.structural_similarity(
            x, y, data_range=data_range, gaussian_weights=True, sigma=1.5,
            use_sample_covariance=False, win_size=11,
        )
    )


def _structured(shape=(48, 56), seed=0) -> np.ndarray:
    """Smooth background, a few disks and an edge: an image with structure at several scales."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    img = 0.2 + 0.3 * np.sin(xx / 7.0) * np.cos(yy / 11.0)
    for _ in range(5):
        cy, cx = rng.uniform(0, shape[0]), rng.uniform(0, shape[1])
        r = rng.uniform(3, 9)
        img += 0.5 * (((yy - cy) ** 2 + (xx - cx) ** 2) < r**2)
    img[:, shape[1] // 2 :] += 0.25
    return img


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a))


# ----------------------------------------------------------------------------------- SSIM


@pytest.mark.parametrize("shape", [(11, 11), (11, 30), (33, 20), (64, 64)])
def test_ssim_matches_skimage_random(shape) -> None:
    rng = np.random.default_rng(sum(shape))
    xs = rng.random((3, *shape)) * 4.0 - 1.0
    ys = xs + rng.standard_normal((3, *shape)) * np.array([0.05, 0.5, 2.0])[:, None, None]
    data_range = 4.0
    got = ssim(_t(xs), _t(ys), data_range=data_range)
    assert got.shape == (3,) and got.dtype == torch.float64
    ref = np.array([_sk_ssim(x, y, data_range) for x, y in zip(xs, ys)])
    np.testing.assert_allclose(got.numpy(), ref, rtol=0, atol=1e-6)
    # The agreement is in fact at the rounding level.
    np.testing.assert_allclose(got.numpy(), ref, rtol=0, atol=1e-12)


def test_ssim_matches_skimage_structured_blurred_shifted() -> None:
    x = _structured()
    y = np.roll(ndimage.gaussian_filter(x, 1.2), (2, -3), axis=(0, 1)) * 0.9 + 0.05
    data_range = float(x.max() - x.min())
    got = ssim(_t(x), _t(y), data_range=data_range)
    assert got.shape == (1,)
    ref = _sk_ssim(x, y, data_range)
    assert 0.2 < ref < 0.95  # a meaningful, intermediate value
    assert abs(got.item() - ref) < 1e-6


def test_ssim_identity_and_monotone_in_noise() -> None:
    x = _structured(seed=3)
    assert ssim(_t(x), _t(x), data_range=1.0).item() == pytest.approx(1.0, abs=1e-12)
    rng = np.random.default_rng(1)
    noise = rng.standard_normal(x.shape)
    values = [ssim(_t(x), _t(x + s * noise), data_range=1.0).item() for s in (0.01, 0.05, 0.2, 1.0)]
    assert all(a > b for a, b in zip(values, values[1:]))
    assert ssim_loss(_t(x), _t(x), data_range=1.0).item() == pytest.approx(0.0, abs=1e-12)


def test_ssim_float32_and_errors() -> None:
    x = _structured()
    y = ndimage.gaussian_filter(x, 1.0)
    got32 = ssim(_t(x).float(), _t(y).float(), data_range=1.0)
    assert got32.dtype == torch.float32
    assert abs(got32.item() - _sk_ssim(x, y, 1.0)) < 1e-4
    with pytest.raises(ValueError, match="smaller than the 11×11"):
        ssim(torch.zeros(10, 20), torch.zeros(10, 20), data_range=1.0)
    with pytest.raises(ValueError, match="same shape"):
        ssim(torch.zeros(20, 20), torch.zeros(20, 21), data_range=1.0)
    with pytest.raises(ValueError, match="data_range"):
        ssim(torch.zeros(20, 20), torch.zeros(20, 20), data_range=0.0)


def test_ssim_gradient_finite() -> None:
    x = _t(_structured()).requires_grad_()
    y = _t(ndimage.gaussian_filter(_structured(), 1.0))
    ssim_loss(x, y, data_range=1.0).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


# ------------------------------------------------------------------------------- L1 / L2


def test_l1_l2_match_numpy() -> None:
    rng = np.random.default_rng(2)
    p, t = rng.standard_normal((2, 4, 9, 7))
    d = p - t
    assert l1_loss(_t(p), _t(t)).item() == pytest.approx(np.mean(np.abs(d)), rel=1e-12)
    assert l2_loss(_t(p), _t(t)).item() == pytest.approx(np.mean(d**2), rel=1e-12)

    # A per-pixel mask shared by all images, with fractional weights.
    m = rng.random((9, 7))
    mb = np.broadcast_to(m, d.shape)
    assert l1_loss(_t(p), _t(t), _t(m)).item() == pytest.approx(
        np.sum(mb * np.abs(d)) / np.sum(mb), rel=1e-12
    )
    assert l2_loss(_t(p), _t(t), _t(m)).item() == pytest.approx(
        np.sum(mb * d**2) / np.sum(mb), rel=1e-12
    )
    # A full-shape mask; float32 inputs.
    m4 = rng.random(d.shape)
    got = l2_loss(_t(p).float(), _t(t).float(), _t(m4).float())
    assert got.dtype == torch.float32
    assert got.item() == pytest.approx(np.sum(m4 * d**2) / np.sum(m4), rel=1e-5)


def test_masked_loss_ignores_zero_weight_pixels() -> None:
    rng = np.random.default_rng(3)
    p, t = rng.standard_normal((2, 2, 8, 8))
    mask = np.zeros((8, 8))
    mask[2:6, 1:5] = 1.0
    p2 = p.copy()
    p2[:, mask == 0] += 1e3 * rng.standard_normal((2, int((mask == 0).sum())))
    for fn in (l1_loss, l2_loss):
        a = fn(_t(p), _t(t), _t(mask)).item()
        b = fn(_t(p2), _t(t), _t(mask)).item()
        assert a == pytest.approx(b, rel=1e-12)
    inside = (p - t)[:, 2:6, 1:5]
    assert l1_loss(_t(p), _t(t), _t(mask)).item() == pytest.approx(np.abs(inside).mean(), rel=1e-12)
    # Boolean mask works the same; an all-zero mask gives 0 (not nan).
    assert l1_loss(_t(p), _t(t), _t(mask > 0)).item() == pytest.approx(np.abs(inside).mean())
    assert l1_loss(_t(p), _t(t), torch.zeros(8, 8, dtype=torch.float64)).item() == 0.0
    with pytest.raises(ValueError, match="mask"):
        l1_loss(_t(p), _t(t), torch.ones(3, 2, 8, 8, dtype=torch.float64))


# ------------------------------------------------------------------------------------- TV


def test_tv_matches_numpy() -> None:
    rng = np.random.default_rng(4)
    v = rng.standard_normal((3, 6, 5))
    ref_xy = (np.abs(np.diff(v, axis=2)).sum() + np.abs(np.diff(v, axis=1)).sum()) / v.size
    ref_z = np.abs(np.diff(v, axis=0)).sum() / v.size
    assert tv_xy(_t(v)).item() == pytest.approx(ref_xy, rel=1e-12)
    assert tv_z(_t(v)).item() == pytest.approx(ref_z, rel=1e-12)
    # Offsets (absolute RI vs Δn) do not matter; constants give 0; one slice gives tv_z = 0.
    assert tv_xy(_t(v + 1.33)).item() == pytest.approx(ref_xy, rel=1e-12)
    const = torch.full((4, 5, 6), 1.4, dtype=torch.float64)
    assert tv_xy(const).item() == 0.0 and tv_z(const).item() == 0.0
    assert tv_z(_t(v[:1])).item() == 0.0
    with pytest.raises(ValueError, match="Z, H, W"):
        tv_xy(torch.zeros(4, 4))


# ------------------------------------------------------------------------------- schedule


def test_l1_l2_schedule() -> None:
    assert l1_l2_weights(0.0) == (0.0, 1.0)
    assert l1_l2_weights(1.0) == (1.0, 0.0)
    assert l1_l2_weights(0.0, total=2.5) == (0.0, 2.5)
    assert l1_l2_weights(1.0, total=2.5) == (2.5, 0.0)
    assert l1_l2_weights(0.25, total=2.0) == pytest.approx((0.5, 1.5))
    for p in np.linspace(-0.5, 1.5, 41):
        a, b = l1_l2_weights(float(p), total=3.0, start=0.2, end=0.7)
        assert a + b == pytest.approx(3.0)
        assert 0.0 <= a <= 3.0
    # Clamping outside [start, end].
    assert l1_l2_weights(0.1, total=3.0, start=0.2, end=0.7) == (0.0, 3.0)
    assert l1_l2_weights(0.9, total=3.0, start=0.2, end=0.7) == (3.0, 0.0)
    assert l1_l2_weights(0.45, total=3.0, start=0.2, end=0.7)[0] == pytest.approx(1.5)
    with pytest.raises(ValueError):
        l1_l2_weights(0.5, start=0.8, end=0.2)


def test_loss_weights_validation() -> None:
    LossWeights(l1_l2_total=0.0, ssim=0.5, tv_xy=1e-3, tv_z=0.0)
    for field, bad in [("ssim", -0.1), ("tv_xy", math.nan), ("tv_z", math.inf),
                       ("l1_l2_total", -1.0)]:
        with pytest.raises(FDTInputError) as info:
            LossWeights(**{field: bad})
        assert info.value.field == field


# ----------------------------------------------------------------------------- total loss


def _problem(dtype=torch.float64):
    rng = np.random.default_rng(5)
    target = torch.tensor(rng.random((2, 16, 16)), dtype=dtype)
    pred = (target + 0.1 * torch.tensor(rng.standard_normal((2, 16, 16)), dtype=dtype))
    volume = 1.33 + 0.01 * torch.tensor(rng.random((3, 16, 16)), dtype=dtype)
    return pred.requires_grad_(), target, volume.requires_grad_()


def test_total_loss_combines_terms() -> None:
    pred, target, volume = _problem()
    w = LossWeights(l1_l2_total=2.0, ssim=0.5, tv_xy=0.1, tv_z=0.2)
    mask = torch.ones(16, 16, dtype=torch.float64)
    mask[:3] = 0
    total, terms = total_loss(pred, target, volume, w, 0.25, mask=mask, data_range=1.0)
    f = as_floats(terms)
    assert set(f) == {"l1", "l2", "ssim_loss", "tv_xy", "tv_z", "total"}
    assert all(isinstance(v, float) for v in f.values())
    assert all(t.ndim == 0 and not t.requires_grad for t in terms.values())
    alpha, beta = l1_l2_weights(0.25, 2.0)
    assert f["l1"] == pytest.approx(l1_loss(pred, target, mask).item())
    assert f["ssim_loss"] == pytest.approx(ssim_loss(pred * mask, target * mask,
                                                     data_range=1.0).item())
    expected = (alpha * f["l1"] + beta * f["l2"] + 0.5 * f["ssim_loss"] + 0.1 * f["tv_xy"]
                + 0.2 * f["tv_z"])
    assert f["total"] == pytest.approx(expected, rel=1e-12)
    assert total.item() == pytest.approx(expected, rel=1e-12)

    total.backward()
    for t in (pred, volume):
        assert torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0


def test_total_loss_skips_zero_weight_terms(monkeypatch) -> None:
    pred, target, volume = _problem(torch.float32)

    def boom(*args, **kwargs):
        raise AssertionError("a zero-weight term was computed")

    for name in ("ssim", "ssim_loss", "tv_xy", "tv_z"):
        monkeypatch.setattr(losses, name, boom)
    w = LossWeights(l1_l2_total=1.0)  # ssim, tv_xy, tv_z weights 0
    total, terms = total_loss(pred, target, volume, w, 0.5, data_range=1.0)
    assert set(terms) == {"l1", "l2", "total"}
    total.backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0

    # At the ends of the schedule α or β is 0, and that term is skipped too.
    monkeypatch.setattr(losses, "l1_loss", boom)
    _, terms = total_loss(pred, target, volume, w, 0.0, data_range=1.0)
    assert set(terms) == {"l2", "total"}
    monkeypatch.undo()
    monkeypatch.setattr(losses, "l2_loss", boom)
    _, terms = total_loss(pred, target, volume, w, 1.0, data_range=1.0)
    assert set(terms) == {"l1", "total"}


def test_total_loss_all_zero_weights() -> None:
    pred, target, volume = _problem()
    total, terms = total_loss(pred, target, volume, LossWeights(l1_l2_total=0.0), 0.5,
                              data_range=1.0)
    assert set(terms) == {"total"} and total.item() == 0.0
    total.backward()  # still part of the graph
    assert torch.equal(pred.grad, torch.zeros_like(pred))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_total_loss_cuda_matches_cpu() -> None:
    pred, target, volume = _problem()
    w = LossWeights(l1_l2_total=1.0, ssim=0.3, tv_xy=0.1, tv_z=0.1)
    _, cpu = total_loss(pred, target, volume, w, 0.3, data_range=1.0)
    _, gpu = total_loss(pred.detach().cuda(), target.cuda(), volume.detach().cuda(), w, 0.3,
                        data_range=1.0)
    for k, v in as_floats(cpu).items():
        assert as_floats(gpu)[k] == pytest.approx(v, rel=1e-9)


# -------------------------------------------------------------------------------- metrics


def test_rmse_psnr_relative_error_hand_values() -> None:
    true = np.zeros((2, 2))
    pred = np.array([[1.0, -1.0], [1.0, -1.0]])
    assert rmse(pred, true) == pytest.approx(1.0)
    assert psnr(pred, true, data_range=10.0) == pytest.approx(20.0)  # 10·log10(100/1)
    assert psnr(true, true, data_range=1.0) == math.inf
    pred = np.array([[3.0, 0.0], [0.0, 0.0]])
    true = np.array([[0.0, 4.0], [0.0, 0.0]])
    assert rmse(pred, true) == pytest.approx(math.sqrt(25.0 / 4))
    assert relative_delta_n_error(pred, true) == pytest.approx(5.0 / 4.0)
    assert relative_delta_n_error(true, true) == 0.0
    with pytest.raises(ValueError, match="zero everywhere"):
        relative_delta_n_error(pred, np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"\(2, 2\).*\(2, 3\)"):
        rmse(np.zeros((2, 2)), np.zeros((2, 3)))


def _phantom_delta_n(shape=(3, 20, 24), seed=6) -> np.ndarray:
    """Δn ≥ 0 on a zero background: smooth blobs in each slice."""
    rng = np.random.default_rng(seed)
    zz, yy, xx = np.indices(shape).astype(np.float64)
    dn = np.zeros(shape)
    for _ in range(4):
        c = rng.uniform(0, 1, 3) * np.array(shape)
        dn += 0.02 * np.exp(-(((yy - c[1]) ** 2 + (xx - c[2]) ** 2) / 12.0 + (zz - c[0]) ** 2))
    dn[dn < 1e-3] = 0.0
    return dn


def test_volume_ssim_is_mean_of_skimage_slices() -> None:
    true = _phantom_delta_n()
    pred = true + 0.002 * np.random.default_rng(7).standard_normal(true.shape)
    ref = np.mean([_sk_ssim(p, t, 0.02) for p, t in zip(pred, true)])
    assert volume_ssim(pred, true, 0.02) == pytest.approx(ref, abs=1e-9)


def test_paper_normalised_metrics() -> None:
    true = _phantom_delta_n()
    assert true.min() == 0.0
    perfect = paper_normalised_metrics(true, true)
    assert perfect["psnr"] == math.inf and perfect["mse"] == 0.0
    assert perfect["ssim"] == pytest.approx(1.0, abs=1e-12)
    # Scale-invariant by construction: twice the truth normalises to the same volume.
    doubled = paper_normalised_metrics(2.0 * true, true)
    assert doubled["mse"] == pytest.approx(0.0, abs=1e-25)
    assert doubled["ssim"] == pytest.approx(1.0, abs=1e-12)
    assert doubled["psnr"] > 200 or doubled["psnr"] == math.inf
    # Negative predictions are clipped before normalisation.
    assert paper_normalised_metrics(2.0 * true - 0.5 * (true == 0), true)["mse"] == pytest.approx(
        0.0, abs=1e-25
    )
    # A hand-checked imperfect case against explicit normalisation and skimage.
    pred = true + 0.003 * np.random.default_rng(8).standard_normal(true.shape)
    p = np.clip(pred, 0, None) / np.clip(pred, 0, None).max()
    t = (true - true.min()) / (true.max() - true.min())
    got = paper_normalised_metrics(pred, true)
    mse = np.mean((p - t) ** 2)
    assert got["mse"] == pytest.approx(mse, rel=1e-12)
    assert got["psnr"] == pytest.approx(10 * np.log10(1 / mse), rel=1e-12)
    assert got["ssim"] == pytest.approx(np.mean([_sk_ssim(a, b, 1.0) for a, b in zip(p, t)]),
                                        abs=1e-9)
    # An all-zero (or all-negative) prediction stays zero: mse = mean(t²).
    zero = paper_normalised_metrics(-np.ones_like(true), true)
    assert zero["mse"] == pytest.approx(np.mean(t**2), rel=1e-12)


def test_ri_metrics() -> None:
    nb = 1.33
    true_dn = _phantom_delta_n()
    pred_dn = 0.8 * true_dn
    out = ri_metrics(nb + pred_dn, nb + true_dn, nb)
    assert set(out) == {"ri_rmse", "relative_delta_n_error", "ri_psnr", "ri_ssim",
                        "paper_normalised"}
    assert out["ri_rmse"] == pytest.approx(np.sqrt(np.mean((0.2 * true_dn) ** 2)), rel=1e-9)
    assert out["relative_delta_n_error"] == pytest.approx(0.2, rel=1e-9)
    rng_ = true_dn.max() - true_dn.min()
    assert out["ri_psnr"] == pytest.approx(
        10 * np.log10(rng_**2 / np.mean((0.2 * true_dn) ** 2)), rel=1e-6
    )
    assert 0 < out["ri_ssim"] < 1
    # Proportional Δn: the paper's normalised metrics are perfect.
    assert out["paper_normalised"]["ssim"] == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(ValueError, match="pred_ri.*true_ri"):
        ri_metrics(np.zeros((2, 12, 12)), np.zeros((3, 12, 12)), nb)
    # Homogeneous truth: relative error undefined (nan), data range falls back to 1.
    flat = ri_metrics(np.full((1, 12, 12), nb + 0.1), np.full((1, 12, 12), nb), nb)
    assert math.isnan(flat["relative_delta_n_error"])
    assert flat["ri_psnr"] == pytest.approx(20.0)  # 10·log10(1/0.01)


def test_image_metrics() -> None:
    meas = _structured((20, 24))[None].repeat(2, axis=0) * np.array([1.0, 2.0])[:, None, None]
    pred = meas * 1.1
    out = image_metrics(pred, meas)
    L = meas.max() - meas.min()
    assert out["image_psnr"] == pytest.approx(10 * np.log10(L**2 / np.mean((0.1 * meas) ** 2)))
    assert out["image_relative_error"] == pytest.approx(0.1, rel=1e-12)
    assert out["image_ssim"] == pytest.approx(
        np.mean([_sk_ssim(p, m, L) for p, m in zip(pred, meas)]), abs=1e-9
    )
    same = image_metrics(meas, meas)
    assert same["image_psnr"] == math.inf and same["image_relative_error"] == 0.0
    assert same["image_ssim"] == pytest.approx(1.0, abs=1e-12)


def test_least_squares_gain() -> None:
    """The closed-form gain minimises Σ m·(g·pred − meas)² per image; masked pixels do not count; a blank prediction gives 0."""
    from napari_fdt.model.gain import least_squares_gain

    gen = torch.Generator().manual_seed(0)
    pred = torch.rand(3, 8, 9, generator=gen, dtype=torch.float64)
    meas = pred * torch.tensor([2.0, 0.5, 3.0], dtype=torch.float64)[:, None, None]
    assert torch.allclose(least_squares_gain(pred, meas), torch.tensor([2.0, 0.5, 3.0], dtype=torch.float64))
    noisy = meas + 0.1 * torch.rand(3, 8, 9, generator=gen, dtype=torch.float64)
    g = least_squares_gain(noisy, pred)
    ref = [float(np.linalg.lstsq(n.reshape(-1, 1).numpy(), p.reshape(-1).numpy(), rcond=None)[0][0]) for n, p in zip(noisy, pred)]
    assert np.allclose(g.numpy(), ref, rtol=1e-12)
    mask = torch.zeros_like(pred)
    mask[:, :4] = 1
    spoiled = meas.clone()
    spoiled[:, 4:] = 100.0
    assert torch.allclose(least_squares_gain(pred, spoiled, mask), least_squares_gain(pred, meas))
    assert least_squares_gain(torch.zeros(2, 3), torch.ones(2, 3)).item() == 0.0


def test_the_masks_broadcast_follows_numpys_rules() -> None:
    """``_broadcast_shape`` (written out: ``torch.broadcast_shapes`` imports sympy on its first call) against NumPy's
    broadcasting on every pair of shapes of up to 2 dims of sizes 0-3; and the masked mean's two errors."""
    import itertools

    from napari_fdt.recon.problem.losses import _broadcast_shape, _weighted_mean

    shapes = [s for n in range(3) for s in itertools.product(range(4), repeat=n)]
    for a, b in itertools.product(shapes, repeat=2):
        try:
            ref = tuple(np.broadcast_shapes(a, b))
        except ValueError:
            ref = None
        assert _broadcast_shape(a, b) == ref, (a, b)
    values = torch.ones(2, 3, 4)
    assert float(_weighted_mean(values * 2, torch.ones(3, 1))) == 2.0
    with pytest.raises(ValueError, match="does not broadcast"):
        _weighted_mean(values, torch.ones(5, 4))
    with pytest.raises(ValueError, match="would enlarge"):
        _weighted_mean(values, torch.ones(7, 2, 3, 4))
