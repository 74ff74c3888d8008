"""Reconstruction and image quality metrics (numpy arrays in, Python floats out).

Volumes are ``(n_slices, H, W)``; refractive indices are absolute, ``Δn = n − n_b``
(``docs/format.md``). SSIM is :func:`napari_fdt.recon.problem.losses.ssim` (Gaussian 11×11 window, σ = 1.5,
population covariances, valid filtering), evaluated in float64 on the CPU; it equals
``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
use_sample_covariance=False)``.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from napari_fdt.recon.problem import losses

__all__ = [
    "image_metrics",
    "paper_normalised_metrics",
    "psnr",
    "relative_delta_n_error",
    "ri_metrics",
    "rmse",
    "volume_ssim",
]


def _pair(pred: object, true: object, names: tuple[str, str] = ("pred", "true")):
    a = np.asarray(pred, dtype=np.float64)
    b = np.asarray(true, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(
            f"shapes differ: {names[0]} has shape {a.shape}, {names[1]} has shape {b.shape}"
        )
    if a.size == 0:
        raise ValueError(f"{names[0]} and {names[1]} are empty (shape {a.shape})")
    return a, b


def _mse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean((a - b) ** 2))


def _psnr_from_mse(mse: float, data_range: float) -> float:
    if not (data_range > 0 and math.isfinite(data_range)):
        raise ValueError(f"data_range must be positive and finite, got {data_range}")
    if mse == 0:
        return math.inf
    return 10.0 * math.log10(data_range**2 / mse)


def rmse(pred: np.ndarray, true: np.ndarray) -> float:
    """Root-mean-square error ``sqrt(mean((pred − true)²))`` over all elements (same shapes)."""
    a, b = _pair(pred, true)
    return math.sqrt(_mse(a, b))


def psnr(pred: np.ndarray, true: np.ndarray, data_range: float) -> float:
    """Peak signal-to-noise ratio ``10·log10(L²/MSE)`` in dB, ``L = data_range``; ``inf`` if MSE = 0."""
    a, b = _pair(pred, true)
    return _psnr_from_mse(_mse(a, b), float(data_range))


def relative_delta_n_error(pred_delta_n: np.ndarray, true_delta_n: np.ndarray) -> float:
    """``‖Δn − Δn_true‖₂ / ‖Δn_true‖₂`` (Frobenius norms over the whole volume).

    Raises
    ------
    ValueError
        If the shapes differ or the true Δn is zero everywhere (the ratio is undefined).
    """
    a, b = _pair(pred_delta_n, true_delta_n, ("pred_delta_n", "true_delta_n"))
    norm = float(np.linalg.norm(b))
    if norm == 0:
        raise ValueError(
            "the true Δn is zero everywhere (a homogeneous volume): the relative Δn error is "
            "undefined; use an absolute error such as rmse instead"
        )
    return float(np.linalg.norm(a - b)) / norm


def _ssim_per_image(a: np.ndarray, b: np.ndarray, data_range: float) -> np.ndarray:
    """SSIM of each 2-D image of ``(N, H, W)`` (or one ``(H, W)``) stacks, float64, CPU."""
    if a.ndim == 2:
        a, b = a[None], b[None]
    if a.ndim != 3:
        raise ValueError(f"expected images (N, H, W) or (H, W), got shape {a.shape}")
    with torch.no_grad():
        values = losses.ssim(
            torch.from_numpy(np.ascontiguousarray(a)),
            torch.from_numpy(np.ascontiguousarray(b)),
            data_range=float(data_range),
        )
    return values.numpy()


def volume_ssim(pred: np.ndarray, true: np.ndarray, data_range: float) -> float:
    """Mean over slices (axis 0) of the 2-D SSIM of :func:`napari_fdt.recon.problem.losses.ssim`.

    ``pred``, ``true``: ``(n_slices, H, W)`` (or one ``(H, W)`` slice), ``H, W ≥ 11``.
    """
    a, b = _pair(pred, true)
    return float(np.mean(_ssim_per_image(a, b, data_range)))


def paper_normalised_metrics(
    pred_delta_n: np.ndarray, true_delta_n: np.ndarray
) -> dict[str, float]:
    """The metrics the paper's authors report, on normalised Δn volumes.

    - prediction: Δn clipped at 0 from below and divided by its maximum (an all-zero prediction
      after clipping stays zero);
    - truth: min-max scaled to [0, 1] (a constant truth becomes all zeros);
    - ``"mse"``: mean squared difference over all voxels of all slices;
    - ``"psnr"``: ``10·log10(1/mse)`` (data range 1; ``inf`` when mse = 0);
    - ``"ssim"``: 2-D SSIM (11×11 Gaussian window, σ = 1.5, data range 1) averaged over slices.

    The prediction's normalisation makes the scores invariant to a positive scale of the
    prediction; they are perfect when the prediction is proportional to a truth that is ≥ 0 with
    a zero background.

    Parameters
    ----------
    pred_delta_n, true_delta_n:
        ``(n_slices, H, W)`` Δn volumes (``H, W ≥ 11``), same shape.
    """
    p, t = _pair(pred_delta_n, true_delta_n, ("pred_delta_n", "true_delta_n"))
    p = np.clip(p, 0.0, None)
    pmax = float(p.max())
    if pmax > 0:
        p = p / pmax
    t = t - float(t.min())
    tmax = float(t.max())
    if tmax > 0:
        t = t / tmax
    mse = _mse(p, t)
    return {
        "psnr": _psnr_from_mse(mse, 1.0),
        "ssim": float(np.mean(_ssim_per_image(p, t, 1.0))),
        "mse": mse,
    }


def ri_metrics(
    pred_ri: np.ndarray, true_ri: np.ndarray, n_background: float
) -> dict[str, float | dict[str, float]]:
    """Metrics of a reconstructed absolute RI volume against the truth.

    Parameters
    ----------
    pred_ri, true_ri:
        Absolute refractive indices ``(n_slices, H, W)`` (``H, W ≥ 11``), same shape.
    n_background:
        ``n_b``; ``Δn = n − n_b``.

    Returns
    -------
    dict with
        ``"ri_rmse"``: RMSE in absolute RI units;
        ``"relative_delta_n_error"``: :func:`relative_delta_n_error` of the Δn volumes
        (``nan`` when the true Δn is zero everywhere);
        ``"ri_psnr"``, ``"ri_ssim"``: PSNR and slice-averaged SSIM with data range
        ``true_ri.max() − true_ri.min()``, or 1.0 when the truth is constant;
        ``"paper_normalised"``: :func:`paper_normalised_metrics` of the Δn volumes.
    """
    p, t = _pair(pred_ri, true_ri, ("pred_ri", "true_ri"))
    nb = float(n_background)
    data_range = float(t.max() - t.min())
    if data_range <= 0:
        data_range = 1.0
    dp, dt = p - nb, t - nb
    try:
        rel = relative_delta_n_error(dp, dt)
    except ValueError:
        rel = math.nan
    return {
        "ri_rmse": math.sqrt(_mse(p, t)),
        "relative_delta_n_error": rel,
        "ri_psnr": _psnr_from_mse(_mse(p, t), data_range),
        "ri_ssim": float(np.mean(_ssim_per_image(p, t, data_range))),
        "paper_normalised": paper_normalised_metrics(dp, dt),
    }


def image_metrics(pred_images: np.ndarray, measured_images: np.ndarray) -> dict[str, float]:
    """Agreement of predicted and measured images ``(N, H, W)`` (or one ``(H, W)``; ``H, W ≥ 11``).

    Returns
    -------
    dict with
        ``"image_psnr"``: PSNR over the whole stack, data range = measured max − min over the
        whole stack (1.0 when the measured stack is constant);
        ``"image_ssim"``: mean over images of the 2-D SSIM with the same data range;
        ``"image_relative_error"``: ``‖pred − meas‖₂ / ‖meas‖₂`` over the stack (``nan`` when the
        measured images are zero everywhere).
    """
    from napari_fdt.data.mapped import chunks

    pred, meas = np.asarray(pred_images), np.asarray(measured_images)
    if pred.shape != meas.shape:
        raise ValueError(f"shapes differ: pred_images has shape {pred.shape}, measured_images has shape {meas.shape}")
    if meas.size == 0:
        raise ValueError(f"pred_images and measured_images are empty (shape {meas.shape})")
    if meas.ndim == 2:
        pred, meas = pred[None], meas[None]
    if meas.ndim != 3:
        raise ValueError(f"expected images (N, H, W) or (H, W), got shape {meas.shape}")
    # chunk by chunk: a memory-mapped measured stack of any pixel type is read once, without float64 copies of its size
    parts = list(chunks(meas, 2**24))
    lo = min(float(np.min(meas[s])) for s in parts)
    hi = max(float(np.max(meas[s])) for s in parts)
    data_range = hi - lo if hi > lo else 1.0
    sq_err = sq_meas = 0.0
    ssim = []
    for s in parts:
        p, m = _pair(pred[s], meas[s], ("pred_images", "measured_images"))
        sq_err += float(np.sum((p - m) ** 2))
        sq_meas += float(np.sum(m * m))
        ssim.append(_ssim_per_image(p, m, data_range))
    return {
        "image_psnr": _psnr_from_mse(sq_err / meas.size, data_range),
        "image_ssim": float(np.mean(np.concatenate(ssim))),
        "image_relative_error": math.sqrt(sq_err) / math.sqrt(sq_meas) if sq_meas > 0 else math.nan,
    }
