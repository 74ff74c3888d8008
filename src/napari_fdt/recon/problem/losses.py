"""Differentiable loss terms for fluorescence diffraction tomography (torch).

The per-image loss of the paper is

    α‖Î − I‖₁ + β‖Î − I‖₂² + γ(1 − SSIM(Î, I)) + τ_xy R_xy(n) + τ_z R_z(n),

with ``R_xy = ‖∇x n‖₁ + ‖∇y n‖₁`` and ``R_z = ‖∇z n‖₁``, and with α rising from 0 while β falls
during the run, α + β constant (:func:`l1_l2_weights`).

Every function here works on CPU and CUDA tensors, in float32 and float64, and is differentiable.
Images are ``(B, H, W)`` (or one ``(H, W)`` image); volumes are ``(Z, H, W)`` with axis 0 the
slices (``docs/format.md``). Scalar results are 0-dim tensors. Nothing in this module calls
``.item()`` or otherwise synchronises with the device; :func:`as_floats` is the one place where
values are brought back to Python floats, to be called only when they are needed (e.g. for logging).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from pydantic import model_validator

from napari_fdt.errors import FDTInputError
from napari_fdt.recon.settings.config import SolverConfig
from napari_fdt.schema import schema_dataclass, setting

__all__ = [
    "BatchShare",
    "LossWeights",
    "as_floats",
    "gaussian_window",
    "l1_l2_weights",
    "l1_loss",
    "l2_loss",
    "ssim",
    "ssim_loss",
    "total_loss",
    "tv_xy",
    "tv_z",
]


# --------------------------------------------------------------------------------------------
# Pixel losses
# --------------------------------------------------------------------------------------------


def _check_same_shape(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.shape != target.shape:
        raise ValueError(
            f"pred and target must have the same shape, got {tuple(pred.shape)} and "
            f"{tuple(target.shape)}"
        )


def _weighted_mean(
    values: torch.Tensor, mask: torch.Tensor | None, denominator: torch.Tensor | float | None = None
) -> torch.Tensor:
    """Mean of ``values``, or ``Σ m·values / Σ m`` with the mask broadcast to ``values``.

    ``denominator`` replaces the count (``values.numel()``, or ``Σ m``): part of a batch normalised by the
    whole batch (:class:`BatchShare`). A zero denominator gives 0 (without a device synchronisation: the
    guard is a ``torch.where``).
    """
    if mask is None:
        if denominator is None:
            return values.mean()
        return _guarded_ratio(values.sum(), denominator)
    mask = torch.as_tensor(mask, device=values.device)
    if mask.dtype == torch.bool or not mask.is_floating_point():
        mask = mask.to(values.dtype)
    shape = _broadcast_shape(tuple(mask.shape), tuple(values.shape))
    if shape is None:
        raise ValueError(
            f"mask of shape {tuple(mask.shape)} does not broadcast to the images' shape "
            f"{tuple(values.shape)}"
        )
    if shape != tuple(values.shape):
        raise ValueError(
            f"mask of shape {tuple(mask.shape)} would enlarge the images' shape "
            f"{tuple(values.shape)} (to {tuple(shape)}); it must broadcast to the images"
        )
    weights = mask.expand(values.shape)
    num = (weights * values).sum()
    return _guarded_ratio(num, weights.sum() if denominator is None else denominator)


def _broadcast_shape(a: tuple[int, ...], b: tuple[int, ...]) -> tuple[int, ...] | None:
    """The broadcast of shapes ``a`` and ``b`` (NumPy's rules), None where they do not broadcast. Written out:
    ``torch.broadcast_shapes`` imports torch's symbolic shapes and sympy on its first call (0.3 s of a cold run)."""
    n = max(len(a), len(b))
    a, b = (1,) * (n - len(a)) + a, (1,) * (n - len(b)) + b
    if any(x != y and 1 not in (x, y) for x, y in zip(a, b)):
        return None
    return tuple(y if x == 1 else x for x, y in zip(a, b))


def _guarded_ratio(num: torch.Tensor, den: torch.Tensor | float) -> torch.Tensor:
    """``num / den``, 0 where ``den`` is not positive."""
    den = torch.as_tensor(den, dtype=num.dtype, device=num.device)
    positive = den > 0
    safe_den = torch.where(positive, den, torch.ones_like(den))
    return torch.where(positive, num / safe_den, torch.zeros_like(num))


def l1_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    denominator: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """Mean absolute error.

    Parameters
    ----------
    pred, target:
        Tensors of the same shape, typically images ``(B, H, W)``.
    mask:
        Optional weights in [0, 1] broadcastable to ``pred.shape`` (e.g. ``(H, W)`` for all images,
        or ``(B, H, W)``). Values are not checked (checking would synchronise with the device).
    denominator:
        Optional count to divide by instead of the number of elements (or ``Σ m``): for a part of a
        batch, the count of the whole batch, so that the parts' losses add up to the batch's
        (:class:`BatchShare`).

    Returns
    -------
    0-dim tensor: ``mean |pred − target|`` over all elements, or with a mask the weighted mean
    ``Σ m·|pred − target| / Σ m`` (the sum of ``m`` taken over the broadcast shape); 0 when
    ``Σ m = 0``.
    """
    _check_same_shape(pred, target)
    return _weighted_mean((pred - target).abs(), mask, denominator)


def l2_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    denominator: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """Mean squared error; same conventions as :func:`l1_loss` with ``(pred − target)²``.

    Returns
    -------
    0-dim tensor: ``mean (pred − target)²``, or ``Σ m·(pred − target)² / Σ m`` (0 when ``Σ m = 0``).
    """
    _check_same_shape(pred, target)
    return _weighted_mean((pred - target).square(), mask, denominator)


# --------------------------------------------------------------------------------------------
# SSIM
# --------------------------------------------------------------------------------------------


def gaussian_window(
    window_size: int = 11,
    sigma: float = 1.5,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """1-D Gaussian window ``exp(−k²/2σ²)``, ``k = −r … r``, ``r = (window_size − 1)/2``, sum 1.

    This is the kernel of ``scipy.ndimage.gaussian_filter(sigma, truncate=t)`` whenever
    ``r = int(t·σ + 0.5)``; scikit-image's SSIM uses ``t = 3.5``, which gives ``r = 5``
    (``window_size = 11``) for ``σ = 1.5``.

    Returns
    -------
    Tensor ``(window_size,)``.
    """
    if window_size < 1 or window_size % 2 != 1:
        raise ValueError(f"window_size must be a positive odd integer, got {window_size}")
    if not (sigma > 0 and math.isfinite(sigma)):
        raise ValueError(f"sigma must be positive and finite, got {sigma}")
    r = (window_size - 1) // 2
    k = torch.arange(-r, r + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (k / sigma) ** 2)
    w = w / w.sum()
    return w.to(dtype=dtype, device=device)


def ssim(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    data_range: float,
    window_size: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) of each image pair, averaged over the SSIM map.

    Local statistics use a normalised separable Gaussian window (:func:`gaussian_window`), applied
    as two 1-D convolutions with "valid" filtering (no padding: the map is
    ``(H − window_size + 1, W − window_size + 1)``), population (not sample) (co)variances, and
    ``C1 = (k1·L)²``, ``C2 = (k2·L)²`` with ``L = data_range``.

    With the defaults this equals ``skimage.metrics.structural_similarity(x, y, data_range=L,
    gaussian_weights=True, sigma=1.5, use_sample_covariance=False, win_size=11)`` (scikit-image
    filters with a Gaussian truncated at radius ``int(3.5·σ + 0.5) = 5`` and then crops 5 pixels
    off each border of its map, which is the same as valid filtering with this window).

    Parameters
    ----------
    x, y:
        Images ``(B, H, W)``, or one image ``(H, W)``; same shape.
    data_range:
        ``L``, the dynamic range of the images (> 0).

    Returns
    -------
    Tensor ``(B,)`` (``(1,)`` for a 2-D input), in the dtype of the inputs.

    Raises
    ------
    ValueError
        If the shapes differ or are not 2-D/3-D, or an image is smaller than the window.
    """
    _check_same_shape(x, y)
    if x.ndim == 2:
        x, y = x.unsqueeze(0), y.unsqueeze(0)
    if x.ndim != 3:
        raise ValueError(f"ssim expects images (B, H, W) or (H, W), got shape {tuple(x.shape)}")
    if not (data_range > 0 and math.isfinite(data_range)):
        raise ValueError(f"data_range must be positive and finite, got {data_range}")
    h, w = x.shape[-2:]
    if h < window_size or w < window_size:
        raise ValueError(
            f"images of {h}×{w} pixels are smaller than the {window_size}×{window_size} SSIM "
            f"window; SSIM needs images of at least {window_size}×{window_size} pixels"
        )
    dtype = torch.promote_types(x.dtype, y.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    x, y = x.to(dtype), y.to(dtype)
    g = gaussian_window(window_size, sigma, dtype=dtype, device=x.device)

    # Five maps filtered at once, one group each: (B, 5, H, W).
    stack = torch.stack((x, y, x * x, y * y, x * y), dim=1)
    stack = F.conv2d(stack, g.view(1, 1, 1, -1).expand(5, 1, 1, window_size), groups=5)
    stack = F.conv2d(stack, g.view(1, 1, -1, 1).expand(5, 1, window_size, 1), groups=5)
    mu_x, mu_y, e_xx, e_yy, e_xy = stack.unbind(dim=1)

    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov_xy = e_xy - mu_x * mu_y
    c1 = (k1 * data_range) ** 2
    c2 = (k2 * data_range) ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    return (num / den).mean(dim=(-2, -1))


def ssim_loss(
    pred: torch.Tensor, target: torch.Tensor, *, data_range: float, n_images: int | None = None
) -> torch.Tensor:
    """``1 − mean(ssim(pred, target))`` over the images: 0-dim tensor (0 for identical images).

    ``pred``, ``target``: ``(B, H, W)`` or ``(H, W)``; see :func:`ssim`. ``n_images``: for a part of a
    batch, the number of images of the whole batch; the result is then ``Σ (1 − ssim) / n_images`` over
    this part's images (0 for an empty part), and the parts add up to the batch's value.
    """
    if n_images is None:
        return 1 - ssim(pred, target, data_range=data_range).mean()
    return (1 - ssim(pred, target, data_range=data_range)).sum() / n_images


# --------------------------------------------------------------------------------------------
# Regularisers
# --------------------------------------------------------------------------------------------


def _check_volume(volume: torch.Tensor) -> None:
    if volume.ndim != 3:
        raise ValueError(f"volume must be (Z, H, W), got shape {tuple(volume.shape)}")


def tv_xy(volume: torch.Tensor) -> torch.Tensor:
    """Lateral anisotropic total variation ``R_xy``.

    ``R_xy = (Σ |n[z, i, j+1] − n[z, i, j]| + Σ |n[z, i+1, j] − n[z, i, j]|) / (Z·H·W)``:
    the sums of the absolute forward differences along x (axis 2) and y (axis 1), over all
    differences that exist (no boundary term), divided by the number of voxels.

    Parameters
    ----------
    volume:
        ``(Z, H, W)``. A constant offset (absolute RI or Δn) does not change the value.

    Returns
    -------
    0-dim tensor.
    """
    _check_volume(volume)
    dx = (volume[:, :, 1:] - volume[:, :, :-1]).abs().sum()
    dy = (volume[:, 1:, :] - volume[:, :-1, :]).abs().sum()
    return (dx + dy) / volume.numel()


def tv_z(volume: torch.Tensor) -> torch.Tensor:
    """Axial anisotropic total variation ``R_z = Σ |n[z+1, i, j] − n[z, i, j]| / (Z·H·W)``.

    Parameters
    ----------
    volume:
        ``(Z, H, W)``; a single slice (Z = 1) gives 0.

    Returns
    -------
    0-dim tensor.
    """
    _check_volume(volume)
    return (volume[1:] - volume[:-1]).abs().sum() / volume.numel()


# --------------------------------------------------------------------------------------------
# Weights and the combined loss
# --------------------------------------------------------------------------------------------


def l1_l2_weights(
    progress: float, total: float = 1.0, start: float = 0.0, end: float = 1.0
) -> tuple[float, float]:
    """The paper's L1/L2 schedule: ``(α, β)`` with α rising linearly and ``α + β = total``.

    ``α = total · clamp((progress − start)/(end − start), 0, 1)``, ``β = total − α``: α is 0 up to
    ``start`` and ``total`` from ``end`` on (``start == end``: a step at ``start``).

    Parameters
    ----------
    progress:
        Fraction of the whole run done, in [0, 1] (values outside are clamped by the formula).
    total:
        ``α + β`` (≥ 0).
    start, end:
        Progress at which α starts rising and at which it reaches ``total``; ``start ≤ end``.
    """
    if not end >= start:
        raise ValueError(f"the schedule needs start ≤ end, got start={start}, end={end}")
    if end == start:
        frac = 1.0 if progress >= end else 0.0
    else:
        frac = min(max((progress - start) / (end - start), 0.0), 1.0)
    alpha = total * frac
    return alpha, total - alpha


@dataclass(frozen=True)
class BatchShare:
    """One process's part of a batch that several processes share (data-parallel reconstruction).

    With a share, :func:`total_loss` normalises the data terms by the *whole* batch, so that the parts'
    losses, and hence their gradients, add up to the loss of the whole batch: L1 and L2 divide this
    part's (masked) sum by ``weight_sum``, the sum of the mask over the whole batch (its number of
    pixels when there is no mask); ``1 − SSIM`` is this part's sum over its images divided by
    ``n_images``; the regularisers, which act on the volume all parts share, enter the loss of the one
    part with ``regularisers`` true and are only reported by the others.
    """

    n_images: int
    weight_sum: torch.Tensor | float
    regularisers: bool

    @classmethod
    def of_batch(
        cls, batch_mask: torch.Tensor | None, batch_shape: tuple[int, ...], regularisers: bool
    ) -> "BatchShare":
        """The share of a part of the batch of images ``batch_shape`` = (B, H, W) whose mask is ``batch_mask``.

        ``weight_sum`` is computed as :func:`l1_loss` computes ``Σ m`` for the whole batch, so one part
        holding the whole batch reproduces it.
        """
        if batch_mask is None:
            weight_sum: torch.Tensor | float = float(math.prod(batch_shape))
        else:
            m = torch.as_tensor(batch_mask)
            if m.dtype == torch.bool or not m.is_floating_point():
                m = m.to(torch.get_default_dtype())
            weight_sum = m.expand(batch_shape).sum()
        return cls(int(batch_shape[0]), weight_sum, bool(regularisers))


@schema_dataclass(frozen=True, root="weights")
class LossWeights:
    """Weights of the loss terms (all ≥ 0 and finite), declared with the settings schema.

    A reconstruction builds them from its validated configuration (:meth:`from_config`); the bounds below are
    the same as :class:`~napari_fdt.recon.settings.config.SolverConfig`'s, for callers of :func:`total_loss` alone.

    Attributes
    ----------
    l1_l2_total:
        ``α + β``, shared by L1 and L2 along the schedule :func:`l1_l2_weights`.
    ssim:
        γ, weight of ``1 − SSIM``.
    tv_xy, tv_z:
        τ_xy and τ_z, weights of :func:`tv_xy` and :func:`tv_z`.
    schedule_start, schedule_end:
        Progress (fractions of the run, 0 ≤ start ≤ end ≤ 1) over which α rises from 0 to
        ``l1_l2_total`` (defaults: the whole run).
    """

    l1_l2_total: float = setting(1.0, ge=0, strict=False, description="α + β", fix="use 0 to switch the term off")
    ssim: float = setting(0.0, ge=0, strict=False, description="γ, weight of 1 − SSIM", fix="use 0 to switch the term off")
    tv_xy: float = setting(0.0, ge=0, strict=False, description="τ_xy, weight of the lateral TV", fix="use 0 to switch the term off")
    tv_z: float = setting(0.0, ge=0, strict=False, description="τ_z, weight of the axial TV", fix="use 0 to switch the term off")
    schedule_start: float = setting(0.0, ge=0, le=1, strict=False, description="progress where α starts rising")
    schedule_end: float = setting(1.0, ge=0, le=1, strict=False, description="progress where α reaches l1_l2_total")

    @model_validator(mode="after")
    def _schedule_in_order(self) -> "LossWeights":
        if not self.schedule_start <= self.schedule_end:
            raise FDTInputError(
                "schedule_end",
                f"the L1/L2 schedule needs 0 ≤ schedule_start ≤ schedule_end ≤ 1, got "
                f"{self.schedule_start} and {self.schedule_end}",
                "give fractions of the run with start ≤ end",
            )
        return self

    @classmethod
    def from_config(cls, config: SolverConfig) -> "LossWeights":
        """The weights of a (validated) solver configuration; a weight set to ``"auto"`` starts at 0 (the solver
        sets it when it has chosen it, :mod:`napari_fdt.recon.loop.regularisation`)."""
        def fixed(w: float | str) -> float:
            return 0.0 if w == "auto" else w
        return cls(config.l1_l2_total, config.ssim_weight, fixed(config.tv_xy_weight), fixed(config.tv_z_weight),
                   config.l1_ramp_start, config.l1_ramp_end)


def total_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    volume: torch.Tensor,
    weights: LossWeights,
    progress: float,
    *,
    mask: torch.Tensor | None = None,
    data_range: float,
    share: BatchShare | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The paper's combined loss.

    ``α·l1 + β·l2 + γ·(1 − SSIM) + τ_xy·tv_xy + τ_z·tv_z`` with ``(α, β)`` from
    :func:`l1_l2_weights` at ``progress``. A term whose weight is 0 (including α or β at the ends
    of the schedule) is not computed at all and is absent from the returned dict.

    Parameters
    ----------
    pred, target:
        Predicted and measured images ``(B, H, W)`` (or ``(H, W)``), same shape.
    volume:
        The RI (or Δn) volume ``(Z, H', W')`` for the regularisers.
    weights:
        :class:`LossWeights`.
    progress:
        Fraction of the run done, in [0, 1].
    mask:
        Optional weights in [0, 1] broadcastable to the images: L1 and L2 are weighted means
        (:func:`l1_loss`), and SSIM is computed on ``pred·mask`` and ``target·mask``
        (the paper's Hadamard product).
    data_range:
        Dynamic range of the images for SSIM (> 0).
    share:
        None for a whole batch. For one process's part of a batch (``pred`` may then hold no image),
        the :class:`BatchShare` that normalises the data terms by the whole batch and says whether
        this part carries the regularisers; summed over the parts, ``total`` and the data terms are
        the whole batch's values. A part without the regularisers still reports them in ``terms``.

    Returns
    -------
    total:
        0-dim tensor, differentiable with respect to ``pred`` and ``volume``.
    terms:
        Detached 0-dim tensors, unweighted, under the keys ``"l1"``, ``"l2"``, ``"ssim_loss"``
        (``1 − SSIM``), ``"tv_xy"``, ``"tv_z"`` (only the computed ones) and ``"total"``.
        Convert with :func:`as_floats` when needed (that synchronises with the device).
    """
    _check_same_shape(pred, target)
    alpha, beta = l1_l2_weights(
        progress, weights.l1_l2_total, weights.schedule_start, weights.schedule_end
    )
    weighted: list[torch.Tensor] = []
    terms: dict[str, torch.Tensor] = {}

    def add(name: str, weight: float, value: torch.Tensor, in_loss: bool = True) -> None:
        terms[name] = value.detach()
        if in_loss:
            weighted.append(weight * value)

    den = None if share is None else share.weight_sum
    n_images = None if share is None else share.n_images
    if alpha > 0:
        add("l1", alpha, l1_loss(pred, target, mask, denominator=den))
    if beta > 0:
        add("l2", beta, l2_loss(pred, target, mask, denominator=den))
    if weights.ssim > 0:
        if mask is not None:
            m = torch.as_tensor(mask, device=pred.device).to(pred.dtype)
            add("ssim_loss", weights.ssim, ssim_loss(pred * m, target * m, data_range=data_range, n_images=n_images))
        else:
            add("ssim_loss", weights.ssim, ssim_loss(pred, target, data_range=data_range, n_images=n_images))
    regularise = share is None or share.regularisers
    if weights.tv_xy > 0:
        add("tv_xy", weights.tv_xy, tv_xy(volume), regularise)
    if weights.tv_z > 0:
        add("tv_z", weights.tv_z, tv_z(volume), regularise)

    if weighted:
        total = weighted[0]
        for term in weighted[1:]:
            total = total + term
    else:
        # Every weight is zero: a zero that still belongs to the graph of pred.
        total = pred.sum() * 0.0
    terms["total"] = total.detach()
    return total, terms


def as_floats(terms: dict[str, torch.Tensor | float]) -> dict[str, float]:
    """``{name: float(value)}``; the tensors (0-d) are read back from the device together: one synchronisation."""
    names = [n for n, v in terms.items() if isinstance(v, torch.Tensor)]
    device = terms[names[0]].device if names else None
    read = torch.stack([terms[n].detach().reshape(()).to(device, torch.float64) for n in names]).tolist() if names else []
    out = {n: float(v) for n, v in terms.items() if not isinstance(v, torch.Tensor)}
    out.update(zip(names, read))
    return {n: out[n] for n in terms}
