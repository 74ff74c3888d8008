"""Independent reference for the camera and objective of docs/physics.md §3 (pupil edge, aberrations, pixels).

Written from docs/physics.md alone (numpy only, no import of ``napari_fdt``), by brute force rather than the
model's shortcuts:

* **hard (or soft) pupil held exactly**: the whole computation runs on a window ``grow`` times wider than the
  documented plan (the pupil's edge tails that wrap around a periodic window decay with its size); the model
  instead replaces the homogeneous part of each field by a Hankel transform;
* **Zernike phase**: ``exp(+i·Σ c_j Z_j(ρ, φ))`` with the Noll polynomials of the documented table, written out
  in polar form (ρ = |f|/(NA/λ), φ = atan2(fy, fx));
* **pixel integration**: the mean intensity over each pixel by Gauss–Legendre quadrature over the pixel's area
  (``order``² sub-pixel points, each field value exact by the Fourier shift theorem); the model instead
  box-filters a 2× finer grid in the Fourier domain.

The multi-slice part (source spectrum, propagation, screens) is that of ``independent_reference.py``.
"""

from __future__ import annotations

import math

import numpy as np

from tests import independent_reference as base

__all__ = ["zernike_phase", "forward_images_optics"]

_NOLL = {
    "defocus": lambda r, p: math.sqrt(3) * (2 * r**2 - 1),
    "astigmatism_oblique": lambda r, p: math.sqrt(6) * r**2 * np.sin(2 * p),
    "astigmatism_vertical": lambda r, p: math.sqrt(6) * r**2 * np.cos(2 * p),
    "coma_vertical": lambda r, p: math.sqrt(8) * (3 * r**3 - 2 * r) * np.sin(p),
    "coma_horizontal": lambda r, p: math.sqrt(8) * (3 * r**3 - 2 * r) * np.cos(p),
    "spherical": lambda r, p: math.sqrt(5) * (6 * r**4 - 6 * r**2 + 1),
}


def zernike_phase(fy: np.ndarray, fx: np.ndarray, na: float, lam: float, aberrations: dict) -> np.ndarray:
    """W(ρ, φ) in radians, Noll-normalised, ρ = |f|/(NA/λ), φ = atan2(fy, fx)."""
    r = np.hypot(fx, fy) / (na / lam)
    p = np.arctan2(fy, fx)
    w = np.zeros(np.broadcast(fy, fx).shape)
    for name, c in aberrations.items():
        w = w + c * _NOLL[name](r, p)
    return w


def _wide_window(optics: dict, shape, src, grow: float) -> tuple[int, int, int, int]:
    win = base.plan_window(optics, shape, src)
    hp = base._fast_even(int(math.ceil(grow * win["Hp"])))
    wp = base._fast_even(int(math.ceil(grow * win["Wp"])))
    return hp, wp, hp // 2 - shape[0] // 2, wp // 2 - shape[1] // 2


def forward_images_optics(optics: dict, ri_volume, sources_um, gains, *, pupil_edge: float = 0.0,
                          aberrations: dict | None = None, pixel_integration: bool = False, grow: float = 5.0,
                          order: int = 4, camera_step: int = 1) -> np.ndarray:
    """Camera images (N, H, W) float64 with the pupil edge ε (0: hard), a Zernike phase and pixel averaging.

    ``camera_step`` > 1: the field's grid (``optics["pixel_size_um"]``, the RI given on it) is that many times finer
    than the camera's; the camera's pixels are centred on every ``camera_step``-th grid point from the first and are
    ``camera_step`` grid pixels wide; images (N, H // camera_step, W // camera_step)."""
    ri = np.asarray(ri_volume, dtype=np.float64)
    src = np.asarray(sources_um, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(gains, dtype=np.float64).reshape(-1)
    n_slices, H, W = ri.shape
    lam, n_b, na = float(optics["wavelength_um"]), float(optics["n_background"]), float(optics["na"])
    dx, dz = float(optics["pixel_size_um"]), float(optics["slice_spacing_um"])
    z_img = float(optics.get("image_plane_um", 0.0) or 0.0)
    k_b = n_b / lam
    Hp, Wp, oy, ox = _wide_window(optics, (H, W), src, grow)
    dn = np.zeros((n_slices, Hp, Wp))
    dn[:, oy:oy + H, ox:ox + W] = ri - n_b
    screens = np.exp(1j * (2.0 * np.pi / lam) * dz * dn)
    fy, fx = base.frequency_grid(Hp, Wp, dx)
    f2 = fx**2 + fy**2
    P = base.pupil(np.sqrt(f2), na, lam, pupil_edge)
    if aberrations:
        P = P * np.exp(1j * zernike_phase(fy, fx, na, lam, aberrations))
    H_dz = base.propagator(f2, k_b, dz)
    H_out = base.propagator(f2, k_b, dz / 2.0 - z_img) * P
    if pixel_integration:  # Gauss–Legendre nodes over the pixel [−dx/2, dx/2]², weights summing to 1
        t, wt = np.polynomial.legendre.leggauss(order)
        half = camera_step * dx / 2
        shifts = [(a * half, b * half, wa * wb / 4) for a, wa in zip(t, wt) for b, wb in zip(t, wt)]
    else:
        shifts = [(0.0, 0.0, 1.0)]
    out = np.zeros((src.shape[0], -(-H // camera_step), -(-W // camera_step)))
    for i in range(src.shape[0]):
        u = np.fft.ifft2(base.source_spectrum(optics, Hp, Wp, src[i]))
        for k in range(n_slices):
            if k > 0:
                u = np.fft.ifft2(np.fft.fft2(u) * H_dz)
            u = u * screens[k]
        spec = np.fft.fft2(u) * H_out
        for sy, sx, wgt in shifts:  # E(x + s): spectrum times exp(+i·2π·f·s)
            E = np.fft.ifft2(spec * np.exp(2j * np.pi * (fy * sy + fx * sx)))
            out[i] += wgt * np.abs(E[oy:oy + H:camera_step, ox:ox + W:camera_step]) ** 2
        out[i] *= g[i]
    return out
