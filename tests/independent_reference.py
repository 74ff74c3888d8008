"""Independent reference implementation of the napari-fdt forward model.

Written from ``docs/format.md`` and ``docs/physics.md`` alone (numpy + math only, no
import of ``napari_fdt``), to check that those documents specify the model completely.

Model (physics.md §2-4): point source built from its Weyl angular spectrum with a
raised-cosine band limit, on a periodic window sized by the documented rule; multi-slice
split step with phase screens at slice centres; propagation to the camera's focal plane;
raised-cosine-edged pupil; intensity times a per-image gain. All arithmetic in
float64/complex128.

Public entry point: :func:`forward_images`.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "band_limit_edges",
    "window_size",
    "plan_window",
    "frequency_grid",
    "source_spectrum",
    "propagator",
    "pupil",
    "forward_images",
]


# Defaults of plan_grid's parameters (physics.md §2): ``pupil_taper`` (ε) and ``taper``.
PUPIL_TAPER = 0.03
TAPER = 0.1


def _sines(na: float, n_b: float, pupil_taper: float = PUPIL_TAPER,
           taper: float = TAPER) -> tuple[float, float]:
    """Sines (s_lo, s_hi) of the band limit's edges (physics.md §2).

    ``s_lo = (1 + pupil_taper)·NA/n_b`` (the pupil's outer edge), ``s_hi = min(s_lo + taper, 0.98)``;
    s_lo must stay at least 0.02 below 0.98.
    """
    s_lo = (1.0 + pupil_taper) * na / n_b
    if s_lo > 0.98 - 0.02 + 1e-12:
        raise ValueError(f"na: (1 + pupil_taper)·NA/n_b = {s_lo:.4f} leaves no room for the roll-off")
    return s_lo, min(s_lo + taper, 0.98)


def band_limit_edges(optics: dict) -> tuple[float, float]:
    """Return (f_lo, f_hi) of the band limit in cycles/µm: ``f = n_b·s/λ`` (physics.md §2)."""
    lam = float(optics["wavelength_um"])
    n_b = float(optics["n_background"])
    s_lo, s_hi = _sines(float(optics["na"]), n_b)
    return n_b * s_lo / lam, n_b * s_hi / lam


def _is_235_smooth(n: int) -> bool:
    """True when n has no prime factor other than 2, 3 and 5."""
    for p in (2, 3, 5):
        while n % p == 0:
            n //= p
    return n == 1


def window_size(n: int, dx: float, p: float, a: float, depth_max: float, thickness: float,
                tan_hi: float, pupil_reach: float = 0.0) -> int:
    """Window pixels along one axis (physics.md §4, "The window").

    ``need = max(n·dx + 2p, (n//2)·dx + dx + p + a + (d_max + T)·tan_hi)``, then the smallest
    even 2-3-5-smooth integer ≥ ``max(n + 2, ceil(need/dx − 1e-9))``; then, for the pupil's tails, the
    smallest such integer ≥ that and ≥ ``ceil(((n//2)·dx + dx + a + pupil_reach)/dx − 1e-9)``.
    """
    need = max(n * dx + 2.0 * p,
               (n // 2) * dx + dx + p + a + (depth_max + thickness) * tan_hi)
    m = _fast_even(max(n + 2, int(math.ceil(need / dx - 1e-9))))
    if m > 16384:
        raise ValueError(f"window of {m} pixels is wider than 16384")
    tail = (n // 2) * dx + dx + a + pupil_reach
    return min(16384, _fast_even(max(m, int(math.ceil(tail / dx - 1e-9)))))


def _fast_even(m: int) -> int:
    while m % 2 or not _is_235_smooth(m):
        m += 1
    return m


def plan_window(optics: dict, shape: tuple[int, int], sources_um: np.ndarray) -> dict:
    """Window sizes and offsets for an image of ``shape`` = (H, W) and all the given sources.

    Returns a dict with ``Hp``, ``Wp``, ``offset_y``, ``offset_x``.
    """
    H, W = shape
    dx = float(optics["pixel_size_um"])
    n_b = float(optics["n_background"])
    na = float(optics["na"])
    lam = float(optics["wavelength_um"])
    T = int(optics["n_slices"]) * float(optics["slice_spacing_um"])
    s_lo, s_hi = _sines(na, n_b)
    tan_lo = s_lo / math.sqrt(1.0 - s_lo ** 2)
    tan_hi = s_hi / math.sqrt(1.0 - s_hi ** 2)
    p = T * tan_lo
    src = np.asarray(sources_um, dtype=np.float64).reshape(-1, 3)
    a_x = float(np.max(np.abs(src[:, 0])))
    a_y = float(np.max(np.abs(src[:, 1])))
    d_max = float(np.max(src[:, 2]))
    # physics.md §4: the periodic copies' defocused discs at the focal plane (distance h_c from the sources)
    # end u = λ/(2·ε·NA) beyond the image (ε the pupil's taper).
    h_c = abs(d_max + T - float(optics.get("image_plane_um", 0.0)))
    pupil_reach = h_c * tan_lo + lam / (2.0 * PUPIL_TAPER * na)
    Hp = window_size(H, dx, p, a_y, d_max, T, tan_hi, pupil_reach)
    Wp = window_size(W, dx, p, a_x, d_max, T, tan_hi, pupil_reach)
    return {"Hp": Hp, "Wp": Wp, "offset_y": Hp // 2 - H // 2, "offset_x": Wp // 2 - W // 2}


def frequency_grid(Hp: int, Wp: int, dx: float) -> tuple[np.ndarray, np.ndarray]:
    """Unshifted FFT frequencies (cycles/µm) as 2-D arrays (fy, fx) of shape (Hp, Wp)."""
    fy = np.fft.fftfreq(Hp)[:, None] / dx
    fx = np.fft.fftfreq(Wp)[None, :] / dx
    return np.broadcast_to(fy, (Hp, Wp)), np.broadcast_to(fx, (Hp, Wp))


def _qz_and_envelope_rate(f2: np.ndarray, k_b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For |f|² = f2 and k_b = n_b/λ (cycles/µm) return (propagating mask, qz, qz − k_b).

    ``qz − k_b`` is computed as ``−|f|²/(qz + k_b)``; outside the mask both are 0.
    """
    prop = f2 < k_b ** 2
    qz = np.where(prop, np.sqrt(np.where(prop, k_b ** 2 - f2, 0.0)), 0.0)
    dq = np.where(prop, -f2 / (qz + k_b), 0.0)
    return prop, qz, dq


def propagator(f2: np.ndarray, k_b: float, z: float) -> np.ndarray:
    """Envelope propagation kernel H(z) = exp(+i·2π·(qz − n_b/λ)·z), 0 for evanescent |f|."""
    prop, _, dq = _qz_and_envelope_rate(f2, k_b)
    return np.where(prop, np.exp(1j * 2.0 * np.pi * dq * z), 0.0).astype(np.complex128)


def pupil(fabs: np.ndarray, na: float, lam: float, eps: float = PUPIL_TAPER) -> np.ndarray:
    """Pupil P(|f|): 1 inside (1 − ε)·NA/λ, raised-cosine edge to 0 at (1 + ε)·NA/λ (§3 step 4)."""
    f_c = na / lam
    if eps <= 0.0:
        return (fabs <= f_c).astype(np.float64)
    a, b = (1.0 - eps) * f_c, (1.0 + eps) * f_c
    t = np.clip((fabs - a) / (b - a), 0.0, 1.0)
    p = 0.5 * (1.0 + np.cos(np.pi * t))
    p = np.where(fabs <= a, 1.0, p)
    return np.where(fabs >= b, 0.0, p)


def _band_limit(fabs: np.ndarray, f_lo: float, f_hi: float) -> np.ndarray:
    """Raised-cosine band limit B(|f|)."""
    t = np.clip((fabs - f_lo) / (f_hi - f_lo), 0.0, 1.0)
    b = 0.5 * (1.0 + np.cos(np.pi * t))
    b = np.where(fabs <= f_lo, 1.0, b)
    return np.where(fabs >= f_hi, 0.0, b)


def source_spectrum(optics: dict, Hp: int, Wp: int, source_um) -> np.ndarray:
    """Discrete spectrum S[m, n] (DFT coefficients) of one source at slice 0's centre.

    ``S = B·i·d·exp(i·2π·(qz − n_b/λ)·(d + Δz/2))·exp(−i·2π·(fx·x + fy·y))·(−1)^(m+n)/(qz·dx²)``.
    Array axis 0 is y (fy), axis 1 is x (fx).
    """
    lam = float(optics["wavelength_um"])
    n_b = float(optics["n_background"])
    dx = float(optics["pixel_size_um"])
    dz = float(optics["slice_spacing_um"])
    x_s, y_s, d = (float(v) for v in source_um)
    k_b = n_b / lam
    fy, fx = frequency_grid(Hp, Wp, dx)
    f2 = fx ** 2 + fy ** 2
    f_lo, f_hi = band_limit_edges(optics)
    B = _band_limit(np.sqrt(f2), f_lo, f_hi)
    prop, qz, dq = _qz_and_envelope_rate(f2, k_b)
    keep = (B > 0) & prop
    safe_qz = np.where(keep, qz, 1.0)
    h = d + dz / 2.0
    iy = np.arange(Hp)[:, None]
    ix = np.arange(Wp)[None, :]
    sign = np.where((iy + ix) % 2 == 0, 1.0, -1.0)
    S = (B * 1j * d * np.exp(1j * 2.0 * np.pi * dq * h)
         * np.exp(-1j * 2.0 * np.pi * (fx * x_s + fy * y_s))
         * sign / (safe_qz * dx ** 2))
    return np.where(keep, S, 0.0).astype(np.complex128)


def forward_images(optics: dict, ri_volume, sources_um, gains, window: dict | None = None) -> np.ndarray:
    """Camera images (N, H, W) float64 of the multi-slice model (physics.md §3-4).

    Parameters
    ----------
    optics : dict
        The ``acquisition.json`` content (wavelength_um, n_background, na, pixel_size_um,
        n_slices, slice_spacing_um, optional image_plane_um).
    ri_volume : array (n_slices, H, W)
        Absolute refractive index; slice 0 nearest the sources.
    sources_um : array (N, 3)
        ``[x, y, depth]`` per image, µm.
    gains : array (N,)
        Gain g_i per image.
    window : dict, optional
        ``Hp``, ``Wp`` (even), ``offset_y``, ``offset_x`` of the periodic window (default: :func:`plan_window`'s), e.g.
        a coarser grid's window in µm, to compare two samplings of one periodic problem.
    """
    ri = np.asarray(ri_volume, dtype=np.float64)
    src = np.asarray(sources_um, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(gains, dtype=np.float64).reshape(-1)
    n_slices, H, W = ri.shape
    if n_slices != int(optics["n_slices"]):
        raise ValueError("ri_volume's slice count differs from optics['n_slices']")
    if g.shape[0] != src.shape[0]:
        raise ValueError("one gain per source is needed")
    lam = float(optics["wavelength_um"])
    n_b = float(optics["n_background"])
    na = float(optics["na"])
    dx = float(optics["pixel_size_um"])
    dz = float(optics["slice_spacing_um"])
    z_img = float(optics.get("image_plane_um", 0.0) or 0.0)
    k_b = n_b / lam

    win = plan_window(optics, (H, W), src) if window is None else window
    Hp, Wp, oy, ox = win["Hp"], win["Wp"], win["offset_y"], win["offset_x"]

    # Phase screens on the window (background outside the image).
    dn = np.zeros((n_slices, Hp, Wp))
    dn[:, oy:oy + H, ox:ox + W] = ri - n_b
    screens = np.exp(1j * (2.0 * np.pi / lam) * dz * dn)

    fy, fx = frequency_grid(Hp, Wp, dx)
    f2 = fx ** 2 + fy ** 2
    H_dz = propagator(f2, k_b, dz)
    H_out = propagator(f2, k_b, dz / 2.0 - z_img) * pupil(np.sqrt(f2), na, lam)

    out = np.empty((src.shape[0], H, W))
    for i in range(src.shape[0]):
        u = np.fft.ifft2(source_spectrum(optics, Hp, Wp, src[i]))
        for k in range(n_slices):
            if k > 0:
                u = np.fft.ifft2(np.fft.fft2(u) * H_dz)
            u = u * screens[k]
        E = np.fft.ifft2(np.fft.fft2(u) * H_out)
        out[i] = g[i] * np.abs(E[oy:oy + H, ox:ox + W]) ** 2
    return out
