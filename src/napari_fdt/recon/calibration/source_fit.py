"""Initial source positions from the images: the paper's per-image 2-D Gaussian fit.

Each image is the light cone of one point source seen through the pupil (a defocused disc,
``docs/physics.md``), modulated by the sample. Following the paper, every image is fitted by least
squares with

    I(x, y) ≈ A · exp(−((x − px)² + (y − py)²) / (2σ²)) + b

(a constant background ``b`` added). The mean ``(px, py)`` estimates the source's lateral position
(x, y from the image centre, ``docs/format.md``); σ grows with the source's height below the camera's
focal plane, ``h = depth + T − image_plane_um`` (T = n_slices·slice_spacing_um). The σ → h relation is
calibrated with the forward model itself (homogeneous medium) and inverted for the depth.

All fits run batched in torch (one Levenberg–Marquardt step for all images at once, a 5×5 solve per
image), deterministic, in float64. Lengths are in µm.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.device import resolve_device
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.render import render_images
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.optics import Optics

__all__ = [
    "GaussianFit",
    "fit_gaussians",
    "calibrate_sigma",
    "depth_from_sigma",
    "initial_sources",
]

#: Default number of Levenberg–Marquardt iterations of :func:`fit_gaussians`.
DEFAULT_ITERATIONS = 60
#: Largest number of Jacobian entries (images × pixels × 5) held at once; larger stacks are fitted in chunks.
_MAX_JACOBIAN_ENTRIES = 1 << 23
# Bounds of the fit, in pixels and in units of each image's peak: a parameter is clamped there, and
# the image is flagged (``GaussianFit.at_bound``) with whatever residual the clamped fit leaves.
_CENTRE_REACH = 3.0  # |px|, |py| <= 3 image sides from the centre
_SIGMA_MIN_PX = 0.25
_SIGMA_MAX_SIDES = 20.0  # σ <= 20 image sides
_AMPLITUDE_RANGE = (1e-8, 1e6)
_BACKGROUND_RANGE = (-10.0, 10.0)


@dataclass
class GaussianFit:
    """Per-image fit ``A·exp(−((x−px)² + (y−py)²)/(2σ²)) + b``, every field (N,) numpy.

    ``x_um``, ``y_um``: the mean (px, py), µm from the image centre (``docs/format.md``);
    ``sigma_um``: σ, µm; ``amplitude`` A and ``background`` b in the images' units;
    ``residual``: relative RMS residual ``‖model − image‖ / ‖image‖``;
    ``at_bound``: True where a parameter ended clamped at the fit's bounds (centre far outside the
    image, σ beyond 20 image sides or below a quarter pixel, …): the fit is not trustworthy there.
    """

    x_um: np.ndarray
    y_um: np.ndarray
    sigma_um: np.ndarray
    amplitude: np.ndarray
    background: np.ndarray
    residual: np.ndarray
    at_bound: np.ndarray

    def __len__(self) -> int:
        return int(self.x_um.shape[0])

    def as_dict(self) -> dict:
        """The fields as lists (JSON-friendly)."""
        return {k: getattr(self, k).tolist() for k in
                ("x_um", "y_um", "sigma_um", "amplitude", "background", "residual", "at_bound")}


def _check_images(images, field: str = "images") -> np.ndarray:
    """(N, H, W) float64 copy of ``images`` (a single (H, W) image becomes N = 1), checked."""
    try:
        arr = np.asarray(images)
    except Exception as exc:  # pragma: no cover - exotic inputs
        raise FDTInputError(field, f"cannot be read as an array ({exc})", "pass a numpy array (N, H, W)") from exc
    if arr.dtype.kind not in "iuf":
        raise FDTInputError(field, f"must hold real numbers, got dtype {arr.dtype}", "pass intensities as float32 or uint16")
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[0] < 1 or arr.shape[1] < 3 or arr.shape[2] < 3:
        raise FDTInputError(field, f"must be a stack (N, H, W) of images at least 3×3, got shape {arr.shape}",
                            "stack one image per source along the first axis")
    arr = arr.astype(np.float64)
    bad = ~np.isfinite(arr)
    if bad.any():
        i = int(np.argmax(bad.reshape(arr.shape[0], -1).any(axis=1)))
        raise FDTInputError(f"{field}[{i}]", "holds NaN or Inf pixels", "replace or mask the bad pixels first")
    peak = arr.reshape(arr.shape[0], -1).max(axis=1)
    blank = ~(peak > 0)
    if blank.any():
        idx = np.flatnonzero(blank)
        shown = ", ".join(str(int(i)) for i in idx[:8]) + (" …" if idx.size > 8 else "")
        raise FDTInputError(
            field,
            f"{idx.size} of {arr.shape[0]} images are blank (no positive pixel): image {shown}",
            "remove the blank images (and their sources) or check the exposure and the offset subtraction",
        )
    return arr


def _gaussian_and_jacobian(theta: torch.Tensor, yy: torch.Tensor, xx: torch.Tensor, jacobian: bool = True):
    """Model (n, P) for parameters ``[px, py, log σ, log A, b]`` (n, 5) on pixel coordinates (P,), and its Jacobian (n, P, 5)."""
    px, py, ls, la, b = (theta[:, k : k + 1] for k in range(5))
    inv_s2 = torch.exp(-2.0 * ls)
    dx = xx - px
    dy = yy - py
    r2 = dx * dx + dy * dy
    ag = torch.exp(la - 0.5 * r2 * inv_s2)  # A·g, computed in the log domain (no overflow of A)
    model = ag + b
    if not jacobian:
        return model, None
    jac = torch.stack(
        (ag * dx * inv_s2, ag * dy * inv_s2, ag * r2 * inv_s2, ag, torch.ones_like(ag)), dim=-1
    )
    return model, jac


def _fit_chunk(data: torch.Tensor, yy: torch.Tensor, xx: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor,
               iterations: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Levenberg–Marquardt on (n, P) images already divided by their peak; returns (theta (n, 5), cost (n,))."""
    n, npix = data.shape
    dtype, device = data.dtype, data.device
    # Initial guess: background from a low quantile, then centroid and second moment of what is above it.
    k = max(1, int(round(0.05 * npix)))
    b0 = torch.kthvalue(data, k, dim=1).values.unsqueeze(1)
    w = torch.clamp(data - b0, min=0.0)
    wsum = w.sum(dim=1, keepdim=True)
    flat = (wsum <= 0).squeeze(1)
    wsafe = torch.where(wsum > 0, wsum, torch.ones_like(wsum))
    px0 = (w * xx).sum(dim=1, keepdim=True) / wsafe
    py0 = (w * yy).sum(dim=1, keepdim=True) / wsafe
    var0 = (w * ((xx - px0) ** 2 + (yy - py0) ** 2)).sum(dim=1, keepdim=True) / (2.0 * wsafe)
    a0 = w.amax(dim=1, keepdim=True)
    # A flat image (nothing above the quantile): a wide Gaussian at the centre.
    side = float(torch.sqrt(torch.tensor(float(npix))))
    px0 = torch.where(flat.unsqueeze(1), torch.zeros_like(px0), px0)
    py0 = torch.where(flat.unsqueeze(1), torch.zeros_like(py0), py0)
    var0 = torch.where(flat.unsqueeze(1), torch.full_like(var0, side * side), var0)
    a0 = torch.where(flat.unsqueeze(1), torch.full_like(a0, 0.5), a0)
    theta = torch.cat((px0, py0, 0.5 * torch.log(torch.clamp(var0, min=1e-12)), torch.log(torch.clamp(a0, min=1e-30)), b0), dim=1)
    theta = torch.minimum(torch.maximum(theta, lower), upper)

    model, _ = _gaussian_and_jacobian(theta, yy, xx, jacobian=False)
    cost = ((model - data) ** 2).sum(dim=1)
    lam = torch.full((n,), 1e-3, dtype=dtype, device=device)
    eye = torch.eye(5, dtype=dtype, device=device)
    for _ in range(int(iterations)):
        model, jac = _gaussian_and_jacobian(theta, yy, xx)
        res = model - data
        jac_t = jac.transpose(1, 2)
        jtj = jac_t @ jac
        grad = (jac_t @ res.unsqueeze(-1)).squeeze(-1)
        diag = torch.diagonal(jtj, dim1=1, dim2=2)
        scale = diag.amax(dim=1).clamp(min=1e-30)
        damp = lam[:, None] * diag + 1e-12 * scale[:, None]
        system = jtj + torch.diag_embed(damp) + 1e-15 * scale[:, None, None] * eye
        step = torch.linalg.solve(system, -grad.unsqueeze(-1)).squeeze(-1)
        step = torch.nan_to_num(step, nan=0.0, posinf=0.0, neginf=0.0)
        trial = torch.minimum(torch.maximum(theta + step, lower), upper)
        trial_model, _ = _gaussian_and_jacobian(trial, yy, xx, jacobian=False)
        trial_cost = ((trial_model - data) ** 2).sum(dim=1)
        accept = torch.isfinite(trial_cost) & (trial_cost < cost)
        theta = torch.where(accept[:, None], trial, theta)
        cost = torch.where(accept, trial_cost, cost)
        lam = torch.where(accept, lam * 0.3, lam * 5.0).clamp(1e-10, 1e10)
    return theta, cost


def fit_gaussians(
    images: np.ndarray,
    pixel_size_um: float,
    *,
    device: str | torch.device | None = "cpu",
    iterations: int = DEFAULT_ITERATIONS,
) -> GaussianFit:
    """Fit ``A·exp(−((x−px)² + (y−py)²)/(2σ²)) + b`` to every image by least squares.

    Parameters
    ----------
    images: (N, H, W) intensities (a single (H, W) image is N = 1); each must have a positive pixel.
    pixel_size_um: pixel size in sample space, µm; pixel (i, j) sits at ``x = (j − W//2)·dx``,
        ``y = (i − H//2)·dx`` (``docs/format.md``).
    device: torch device of the computation (``"auto"``: CUDA when available).
    iterations: Levenberg–Marquardt iterations (fixed count: the result is deterministic).

    Returns
    -------
    :class:`GaussianFit`. The initial guess is the centroid and second moment of each image above its
    5 % quantile; then all images are refined together by Levenberg–Marquardt on
    ``[px, py, log σ, log A, b]`` (σ and A stay positive), one damped 5×5 solve per image and
    iteration, in float64. Parameters are clamped to generous bounds (centre within 3 image sides of
    the centre, σ between a quarter pixel and 20 image sides): a disc larger than the image or a source
    far outside it gives no NaN but a flagged (``at_bound``) or poorly determined fit.
    """
    if isinstance(pixel_size_um, bool) or not isinstance(pixel_size_um, (int, float, np.integer, np.floating)) \
            or not (math.isfinite(float(pixel_size_um)) and float(pixel_size_um) > 0):
        raise FDTInputError("pixel_size_um", f"must be a positive number, got {pixel_size_um!r}", "give the pixel size in sample space, µm")
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 1:
        raise FDTInputError("iterations", f"must be a whole number >= 1, got {iterations!r}", f"use the default {DEFAULT_ITERATIONS}")
    dx = float(pixel_size_um)
    arr = _check_images(images)
    n, h, w = arr.shape
    dev = resolve_device(device)
    dtype = torch.float64
    peak = arr.reshape(n, -1).max(axis=1)
    yy = ((torch.arange(h, dtype=dtype, device=dev) - h // 2).reshape(h, 1) * torch.ones(1, w, dtype=dtype, device=dev)).reshape(1, -1)
    xx = ((torch.arange(w, dtype=dtype, device=dev) - w // 2).reshape(1, w) * torch.ones(h, 1, dtype=dtype, device=dev)).reshape(1, -1)
    side = float(max(h, w))
    lower = torch.tensor([-_CENTRE_REACH * side, -_CENTRE_REACH * side, math.log(_SIGMA_MIN_PX),
                          math.log(_AMPLITUDE_RANGE[0]), _BACKGROUND_RANGE[0]], dtype=dtype, device=dev)
    upper = torch.tensor([_CENTRE_REACH * side, _CENTRE_REACH * side, math.log(_SIGMA_MAX_SIDES * side),
                          math.log(_AMPLITUDE_RANGE[1]), _BACKGROUND_RANGE[1]], dtype=dtype, device=dev)
    chunk = max(1, _MAX_JACOBIAN_ENTRIES // (5 * h * w))
    thetas, costs = [], []
    with torch.no_grad():
        for start in range(0, n, chunk):
            part = torch.as_tensor(arr[start : start + chunk] / peak[start : start + chunk, None, None],
                                   dtype=dtype, device=dev).reshape(-1, h * w)
            theta, cost = _fit_chunk(part, yy, xx, lower, upper, iterations)
            thetas.append(theta.cpu())
            costs.append(cost.cpu())
    theta = torch.cat(thetas).numpy()
    cost = torch.cat(costs).numpy()
    norm2 = (arr.reshape(n, -1) / peak[:, None]) ** 2
    residual = np.sqrt(cost / norm2.sum(axis=1))
    lo, hi = lower.cpu().numpy(), upper.cpu().numpy()
    tol = 1e-6 * (np.abs(lo) + np.abs(hi))
    at_bound = ((theta <= lo + tol) | (theta >= hi - tol)).any(axis=1)
    return GaussianFit(
        x_um=theta[:, 0] * dx,
        y_um=theta[:, 1] * dx,
        sigma_um=np.exp(theta[:, 2]) * dx,
        amplitude=np.exp(theta[:, 3]) * peak,
        background=theta[:, 4] * peak,
        residual=residual,
        at_bound=at_bound,
    )


# -- σ → depth ------------------------------------------------------------------------------------
#: The calibration stops where the light cone's radius h·tanθ reaches this fraction of half the image's
#: smaller side: beyond, the disc is cut by the image border and σ stops tracking the height (measured on
#: 64×64 images at NA 0.8: σ/h stays 0.39-0.49 up to 0.7 of the half side, then jumps erratically).
FILL_LIMIT = 0.8
#: Fitted σ up to this factor beyond the calibrated range are extrapolated; larger σ are not identifiable.
_EXTRAPOLATE = 1.15
#: Smallest calibrated light-cone radius, pixels.
_MIN_RADIUS_PX = 3.0
#: Number of reference depths of the calibration.
N_REFERENCE = 12


def _cone_tangent(optics: Optics) -> float:
    s = optics.na / optics.n_background
    return s / math.sqrt(1.0 - s * s)


def _check_shape(image_shape) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in image_shape)
    except Exception as exc:
        raise FDTInputError("image_shape", f"must be (H, W), got {image_shape!r}", "give the images' height and width in pixels") from exc
    if h < 8 or w < 8:
        raise FDTInputError("image_shape", f"must be at least 8×8 pixels, got {h}×{w}", "give the images' (H, W)")
    return h, w


def calibrate_sigma(
    optics: Optics, image_shape: tuple[int, int], *, device: str | torch.device | None = "cpu",
    n_reference: int = N_REFERENCE,
) -> dict:
    """Calibrate the fitted σ against the source's height with the forward model itself.

    Renders noise-free images of a centred source in a homogeneous medium (Δn = 0) at ``n_reference``
    depths, fits them with :func:`fit_gaussians` and returns a dict:

    ``reference_depth_um``, ``reference_height_um`` (``h = depth + T − image_plane_um``), ``sigma_um``:
    the calibration points that are kept (σ strictly increasing with h); ``sigma_max_um``, ``depth_max_um``:
    the end of the identifiable range; ``depth_fill_um``: the depth at which the light cone's radius reaches
    :data:`FILL_LIMIT` of half the image (deeper sources fill the image); ``linear``: the least-squares
    line ``σ = a·h + b`` with its largest relative deviation (for information: σ/h grows with h, from the
    diffraction limit at small h to the cut of the image border, so the inversion interpolates the points
    piecewise-linearly instead); ``identifiable``: False when no source deeper than the volume's bottom
    face gives a disc inside the image (``reason`` says why).
    """
    h_px, w_px = _check_shape(image_shape)
    dx = optics.pixel_size_um
    tan = _cone_tangent(optics)
    offset = optics.thickness_um - optics.image_plane_um  # h = depth + offset
    half = (min(h_px, w_px) // 2) * dx
    h_hi = FILL_LIMIT * half / tan
    h_lo = _MIN_RADIUS_PX * dx / tan
    depth_fill = h_hi - offset
    cal = {
        "model": "piecewise-linear",
        "cone_tangent": tan,
        "height_offset_um": offset,
        "fill_limit": FILL_LIMIT,
        "depth_fill_um": depth_fill,
        "reference_depth_um": np.zeros(0),
        "reference_height_um": np.zeros(0),
        "sigma_um": np.zeros(0),
        "reference_residual": np.zeros(0),
        "sigma_max_um": float("nan"),
        "depth_max_um": float("nan"),
        "linear": None,
        "identifiable": False,
        "reason": "",
    }
    if depth_fill <= 0:
        cal["reason"] = (
            f"even a source right at the volume's bottom face is {offset:g} µm below the camera's focal plane: its "
            f"light cone (radius {offset * tan:.1f} µm at NA {optics.na:g}) fills the {min(h_px, w_px) * dx:.1f} µm image"
        )
        return cal
    d_lo = max(h_lo - offset, 0.02 * depth_fill)
    n_ref = max(3, int(n_reference))
    depths = np.geomspace(d_lo, depth_fill, n_ref) if d_lo < depth_fill else np.array([depth_fill])
    src = np.column_stack([np.zeros_like(depths), np.zeros_like(depths), depths])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FDTWarning)  # sampling warnings belong to the acquisition's own run
        plan = plan_for_sources(optics, (h_px, w_px), src, warn=False)
        model = MultiSliceModel(optics, plan, device=device, dtype=torch.float64)
    images = render_images(model, np.zeros((optics.n_slices, h_px, w_px)), src)
    fit = fit_gaussians(images, dx, device=device)
    sigma = fit.sigma_um
    keep = np.ones(depths.size, dtype=bool)
    for k in range(depths.size):  # keep the increasing prefix: σ must track the height
        if fit.at_bound[k] or (k and not (sigma[k] > sigma[k - 1] and keep[k - 1])):
            keep[k:] = False
            break
    depths, sigma, residual = depths[keep], sigma[keep], fit.residual[keep]
    heights = depths + offset
    if depths.size < 2:
        cal["reason"] = "the fitted σ does not grow with depth over the range where the disc fits in the image"
        return cal
    a, b = np.polyfit(heights, sigma, 1)
    deviation = float(np.max(np.abs(a * heights + b - sigma) / sigma))
    cal.update(
        reference_depth_um=depths, reference_height_um=heights, sigma_um=sigma, reference_residual=residual,
        sigma_max_um=float(sigma[-1]), depth_max_um=float(depths[-1]),
        linear={"slope": float(a), "intercept_um": float(b), "max_relative_deviation": deviation},
        identifiable=True,
    )
    return cal


def _invert(sigma_um: np.ndarray, cal: dict) -> tuple[np.ndarray, np.ndarray]:
    """Depths (N,) and identifiable mask from σ with a calibration of :func:`calibrate_sigma`.

    Inside the calibrated σ range: piecewise-linear interpolation of h(σ). Below it: h ∝ σ through the
    first point. Up to :data:`_EXTRAPOLATE` beyond it: the last segment extended. Beyond (or when the
    calibration is not identifiable): not identifiable, the depth returned is :func:`_depth_bound` (a lower
    bound: the source's light cone fills the image), or NaN when there is none.
    """
    sigma = np.asarray(sigma_um, dtype=np.float64).reshape(-1)
    offset = cal["height_offset_um"]
    fallback = _depth_bound(cal)
    if not cal["identifiable"]:
        return np.full(sigma.shape, fallback), np.zeros(sigma.shape, dtype=bool)
    s_ref, h_ref = cal["sigma_um"], cal["reference_height_um"]
    h = np.interp(sigma, s_ref, h_ref)
    low = sigma < s_ref[0]
    h[low] = h_ref[0] * sigma[low] / s_ref[0]
    high = sigma > s_ref[-1]
    slope = (h_ref[-1] - h_ref[-2]) / (s_ref[-1] - s_ref[-2])
    h[high] = h_ref[-1] + slope * (sigma[high] - s_ref[-1])
    identifiable = np.isfinite(sigma) & (sigma > 0) & (sigma <= _EXTRAPOLATE * s_ref[-1])
    depth = h - offset
    # σ below that of a source at the bottom face: the source is (almost) at the face.
    floor = 0.01 * cal["reference_depth_um"][0] if offset > 0 else 1e-3
    depth = np.maximum(depth, floor)
    depth[~identifiable] = fallback
    return depth, identifiable


def _depth_bound(cal: dict) -> float:
    """Depth beyond which σ no longer tracks the depth (the calibration's last point), or NaN if none."""
    if cal["identifiable"]:
        return float(cal["depth_max_um"])
    return float(cal["depth_fill_um"]) if cal["depth_fill_um"] > 0 else float("nan")


def _not_identifiable_message(count: int, total: int, cal: dict, why: str) -> str:
    lim = _depth_bound(cal)
    bound = f"sources deeper than about {lim:.1f} µm light" if lim > 0 else "every source lights"
    return (
        f"depth is not identifiable from the images for {count} of {total} sources: {why} "
        f"({bound} a disc wider than the image, so σ no longer tracks the depth). "
        "Give the depths yourself: a depth guess (initial_sources(..., depth_um=...)) or "
        "sources_um in acquisition.json"
        + (f"; the depth returned for them is only the lower bound {lim:.1f} µm" if lim > 0 else "")
    )


def depth_from_sigma(
    sigma_um: np.ndarray, optics: Optics, image_shape: tuple[int, int], *, device: str | torch.device | None = "cpu"
) -> tuple[np.ndarray, dict]:
    """Source depths (N,) µm from fitted Gaussian widths σ (N,) µm, calibrated with the forward model.

    The calibration (:func:`calibrate_sigma`) renders a centred source in a homogeneous medium at
    reference depths from a 3-pixel light cone up to one whose radius is :data:`FILL_LIMIT` of half the
    image, fits σ and inverts σ(h) by piecewise-linear interpolation (``h = depth + T − image_plane_um``;
    sources are assumed below the camera's focal plane). Returns ``(depths, calibration)``: the dict of
    :func:`calibrate_sigma` plus ``identifiable_sources`` (N,) bool. σ beyond the calibrated range (the
    disc fills the image) is not identifiable: :class:`FDTWarning`, and the depth returned is the lower
    bound ``depth_max_um`` (NaN when even the shallowest source fills the image).

    σ alone cannot always tell a disc that fills the image: its fit may land anywhere, also inside the
    calibrated range. :func:`initial_sources` also looks at the image border and flags those images.
    """
    if not isinstance(optics, Optics):
        raise FDTInputError("optics", f"must be an Optics, got {type(optics).__name__}", "build it with Optics(...)")
    try:
        sigma = np.asarray(sigma_um, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise FDTInputError("sigma_um", f"must be an array of numbers ({exc})", "pass GaussianFit.sigma_um") from exc
    bad = ~(np.isfinite(sigma) & (sigma > 0))
    if sigma.size == 0 or bad.any():
        where = f"sigma_um[{int(np.argmax(bad))}]" if bad.any() else "sigma_um"
        raise FDTInputError(where, "must hold positive finite widths" + ("" if sigma.size else ", got none"),
                            "pass the σ of fit_gaussians, µm")
    cal = calibrate_sigma(optics, image_shape, device=device)
    depth, identifiable = _invert(sigma, cal)
    cal["identifiable_sources"] = identifiable
    if not identifiable.all():
        why = cal["reason"] or f"σ up to {sigma.max():.2f} µm exceeds the largest calibrated σ {cal['sigma_max_um']:.2f} µm"
        warnings.warn(_not_identifiable_message(int((~identifiable).sum()), sigma.size, cal, why), FDTWarning, stacklevel=2)
    return depth, cal


# -- initial positions ----------------------------------------------------------------------------
#: An image whose border pixels have a median above this fraction of its 99th percentile is lit all
#: over: the source's disc fills the image (measured: ≤ 0.02 for discs inside a 64×64 image, 0.35-0.5
#: for discs wider than it, letters scene with noise).
EDGE_FILL_THRESHOLD = 0.15
#: An image holding less than this fraction of the median image's total light has no usable disc
#: (source far outside the field of view, or a dark frame).
MIN_SIGNAL_FRACTION = 0.05


def _edge_fraction(images: np.ndarray) -> np.ndarray:
    n = images.shape[0]
    border = np.concatenate(
        [images[:, 0, :], images[:, -1, :], images[:, 1:-1, 0], images[:, 1:-1, -1]], axis=1
    )
    top = np.percentile(images.reshape(n, -1), 99, axis=1)
    return np.median(border, axis=1) / np.where(top > 0, top, 1.0)


def initial_sources(
    acquisition: Acquisition, *, depth_um: float | None = None, device: str | torch.device | None = "cpu"
) -> tuple[np.ndarray, dict]:
    """Initial source positions (N, 3) ``[x, y, depth]`` µm from the images alone.

    x, y: the centre of each image's Gaussian fit (:func:`fit_gaussians`). depth: ``depth_um`` for every
    source when given, else from the fitted σ (:func:`calibrate_sigma`, as in :func:`depth_from_sigma`).

    Returns ``(sources, report)``, ``report`` holding

    - ``fit``: the :class:`GaussianFit`; ``residual`` (N,): its relative RMS residuals;
    - ``edge_fraction`` (N,): median of the border pixels over the 99th percentile; ``filled`` (N,) bool:
      above :data:`EDGE_FILL_THRESHOLD`, the disc fills the image (depth not identifiable, x, y less
      accurate);
    - ``signal_fraction`` (N,): each image's total over the median image's total;
    - ``lateral_reliable`` (N,) bool: the fit ended inside the image, away from its bounds, on an image
      holding light (``signal_fraction`` ≥ :data:`MIN_SIGNAL_FRACTION`);
    - ``depth_source``: ``"depth_um"`` or ``"sigma"``; ``depth_identifiable`` (N,) bool;
      ``calibration``: the :func:`calibrate_sigma` dict (``None`` when ``depth_um`` is given).

    Unreliable lateral fits are clipped to the image's extent in ``sources`` (raw values in ``fit``).
    Sources whose depth is not identifiable (disc filling the image, σ beyond the calibration, unreliable
    fit) get the median depth of the identified ones, or the lower bound ``depth_max_um`` when none is
    identified, with an :class:`FDTWarning` saying to give ``depth_um`` or ``sources_um``. Unreliable
    lateral fits also warn. Raises :class:`FDTInputError` for blank images or an invalid ``depth_um``.
    """
    if not isinstance(acquisition, Acquisition):
        raise FDTInputError("acquisition", f"must be an Acquisition, got {type(acquisition).__name__}",
                            "read it with napari_fdt.read_acquisition(folder)")
    if depth_um is not None:
        ok = not isinstance(depth_um, bool) and isinstance(depth_um, (int, float, np.integer, np.floating))
        if not ok or not (math.isfinite(float(depth_um)) and float(depth_um) > 0):
            raise FDTInputError("depth_um", f"must be a positive number, got {depth_um!r}",
                                "give the sources' depth below the volume's bottom face, µm")
    optics = acquisition.optics
    images = acquisition.images_float32()
    fit = fit_gaussians(images, optics.pixel_size_um, device=device)
    n, h_px, w_px = images.shape
    dx = optics.pixel_size_um
    images64 = images.astype(np.float64)
    edge = _edge_fraction(images64)
    filled = edge > EDGE_FILL_THRESHOLD
    totals = np.clip(images64, 0, None).reshape(n, -1).sum(axis=1)
    signal = totals / max(float(np.median(totals)), 1e-300)
    half_x, half_y = (w_px / 2) * dx, (h_px / 2) * dx
    inside = (np.abs(fit.x_um) <= half_x) & (np.abs(fit.y_um) <= half_y)
    lateral_reliable = inside & ~fit.at_bound & (signal >= MIN_SIGNAL_FRACTION)
    report = {
        "fit": fit,
        "residual": fit.residual,
        "edge_fraction": edge,
        "filled": filled,
        "signal_fraction": signal,
        "lateral_reliable": lateral_reliable,
        "calibration": None,
    }
    if not lateral_reliable.all():
        bad = np.flatnonzero(~lateral_reliable)
        warnings.warn(
            f"{bad.size} of {n} images ({', '.join(map(str, bad[:8]))}{' …' if bad.size > 8 else ''}): the Gaussian "
            "fit puts the source outside the image, ended at its bounds or found almost no light; their x, y are "
            "unreliable (give sources_um for them, or drop those images)",
            FDTWarning, stacklevel=2,
        )
    if depth_um is not None:
        depth = np.full(n, float(depth_um))
        report.update(depth_source="depth_um", depth_identifiable=np.ones(n, dtype=bool))
    else:
        cal = calibrate_sigma(optics, (h_px, w_px), device=device)
        depth, in_range = _invert(fit.sigma_um, cal)
        identifiable = in_range & ~filled & lateral_reliable
        if (~identifiable).any():
            if identifiable.any():
                # Sources of one sample sit at similar depths: the identified ones' median beats the bound.
                fallback, what = float(np.median(depth[identifiable])), "the median depth of the others"
            elif _depth_bound(cal) > 0:
                fallback, what = _depth_bound(cal), "only a lower bound"
            else:
                fallback, what = optics.slice_spacing_um, "an arbitrary guess (one slice spacing)"
            depth = np.where(identifiable, depth, fallback)
            reasons = []
            if cal["reason"]:
                reasons.append(cal["reason"])
            else:
                if filled.any():
                    reasons.append(f"{int(filled.sum())} image(s) lit up to the border")
                beyond = ~in_range & ~filled
                if beyond.any():
                    reasons.append(f"σ beyond the largest calibrated {cal['sigma_max_um']:.2f} µm in {int(beyond.sum())} image(s)")
                loose = ~lateral_reliable & in_range & ~filled
                if loose.any():
                    reasons.append(f"unreliable fits in {int(loose.sum())} image(s)")
            msg = _not_identifiable_message(int((~identifiable).sum()), n, cal, "; ".join(reasons))
            msg = msg.split("; the depth returned")[0] + f"; they get the depth {fallback:.1f} µm for now ({what})"
            warnings.warn(msg, FDTWarning, stacklevel=2)
        cal["identifiable_sources"] = identifiable
        report.update(depth_source="sigma", depth_identifiable=identifiable, calibration=cal)
    # Unreliable fits may have run far outside the field: keep their guess within the image (the raw
    # values stay in report["fit"]), so the guess does not blow up the forward model's window.
    x = np.where(lateral_reliable, fit.x_um, np.clip(fit.x_um, -half_x, half_x))
    y = np.where(lateral_reliable, fit.y_um, np.clip(fit.y_um, -half_y, half_y))
    sources = np.column_stack([x, y, depth])
    return sources, report
