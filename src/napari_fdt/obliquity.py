"""Obliquity of the thin phase screen: the exact slab phase, and a per-source correction.

A thin screen gives every plane-wave component crossing a slab of thickness T and contrast Δn the same phase
``2π·T·Δn/λ``. The exact (reflection-free) slab phase of the component of lateral frequency f is

    φ_exact(f) = 2π·T·(sqrt((n_b + Δn)²/λ² − f²) − sqrt(n_b²/λ² − f²)) = 2π·T·Δn/(λ·cos θ) + O(Δn²),

with ``sin θ = λ·f/n_b``: the screen under-counts the path of oblique light by ``1/cos θ − 1`` (6 % at
NA 0.45 in water, 41 % at 0.94). Splitting the slab into more slices does not help: for a laterally uniform
slab the screens commute with the propagation, and the model's phase is ``2π·T·Δn/λ`` whatever the slice count
(``benchmarks/obliquity.py``, ``docs/physics.md`` §6).

Point-source light crosses slice k at lateral offset ``r`` from its source at the ray angle
``tan θ = r/h`` (h the height above the source). :func:`oblique_camera_field` is the multi-slice model with
each source's screens scaled by ``1/cos θ`` of that ray (first order in Δn, exact for the direct wave of a
uniform slab up to diffraction), measured in ``benchmarks/obliquity.py``; the same correction is offered by
``MultiSliceModel(..., obliquity="per_source")`` and the solver setting ``obliquity_correction``.
"""

from __future__ import annotations

import math

import torch

from .propagation import phase_screen

__all__ = ["slab_phase_exact", "screen_phase", "obliquity_error", "ray_secant", "oblique_camera_field",
           "secant_screen_camera_field"]


def slab_phase_exact(f2, delta_n: float, thickness_um: float, n_background: float, wavelength_um: float):
    """Exact extra phase (rad) of plane-wave components of squared lateral frequency ``f2`` crossing a uniform slab.

    ``2π·T·(sqrt((n_b + Δn)²/λ² − f²) − sqrt(n_b²/λ² − f²))``, written as a difference of squares over a sum
    (no cancellation); torch tensors or numpy arrays. Components evanescent in the background are not defined.
    """
    k0 = n_background / wavelength_um
    k1 = (n_background + delta_n) / wavelength_um
    lib = torch if isinstance(f2, torch.Tensor) else __import__("numpy")
    q0 = lib.sqrt(k0 * k0 - f2)
    q1 = lib.sqrt(k1 * k1 - f2)
    return 2.0 * math.pi * thickness_um * (k1 * k1 - k0 * k0) / (q1 + q0)


def screen_phase(delta_n: float, thickness_um: float, wavelength_um: float) -> float:
    """The thin screens' phase for the same slab, any slice count: ``2π·T·Δn/λ`` (rad)."""
    return 2.0 * math.pi * thickness_um * delta_n / wavelength_um


def obliquity_error(sin_theta, delta_n: float, n_background: float):
    """``φ_exact/φ_screen − 1`` at the angle ``sin θ`` in the background (exact in Δn; → ``1/cos θ − 1`` as Δn → 0)."""
    lib = torch if isinstance(sin_theta, torch.Tensor) else __import__("numpy")
    s2 = sin_theta * sin_theta
    n0, n1 = n_background, n_background + delta_n
    # (sqrt(n1² − n0²s²) − n0·cos θ)/Δn − 1, λ and T cancel
    return (n1 * n1 - n0 * n0) / (delta_n * (lib.sqrt(n1 * n1 - n0 * n0 * s2) + n0 * lib.sqrt(1.0 - s2))) - 1.0


def ray_secant(model, sources_um: torch.Tensor, height_um: torch.Tensor | float, *, max_sine: float | None = None) -> torch.Tensor:
    """``1/cos θ`` of the ray from each source to every window pixel at ``height_um`` above the bottom face, (B, Hp, Wp).

    ``tan θ = r / (depth + height)``, r the lateral distance from the source (window coordinates, pixel (i, j) at
    ``((i − Hp/2)·dx, (j − Wp/2)·dx)``); capped at the band limit's angle (``max_sine``, default the plan's f_hi).
    """
    hp, wp = model.plan.padded_shape
    dx = model.pixel_size_um
    dev, dt = model.device, model.dtype
    y = ((torch.arange(hp, device=dev, dtype=dt) - hp // 2) * dx).reshape(1, hp, 1)
    x = ((torch.arange(wp, device=dev, dtype=dt) - wp // 2) * dx).reshape(1, 1, wp)
    src = sources_um.to(dev, dt)
    h = (src[:, 2] + height_um).reshape(-1, 1, 1)
    r2 = (x - src[:, 0].reshape(-1, 1, 1)) ** 2 + (y - src[:, 1].reshape(-1, 1, 1)) ** 2
    sec = torch.sqrt(1.0 + r2 / (h * h))
    if max_sine is None:
        max_sine = model.plan.f_hi_per_um * model.optics.wavelength_um / model.optics.n_background
    return torch.clamp(sec, max=1.0 / math.sqrt(1.0 - max_sine**2))


def oblique_camera_field(model, delta_n: torch.Tensor, sources_um: torch.Tensor) -> torch.Tensor:
    """Proposal: :meth:`MultiSliceModel.camera_field` with slice k's screen for source i raised to ``1/cos θ_i``.

    Same kernels, source spectrum, pupil and crop as ``model`` (the acquisition's optics); the screen of slice k
    becomes ``exp(i·2π/λ·Δz·Δn·sec θ_i(x, y, z_k))`` with ``z_k = (k + ½)·Δz``. Cost: the screen is per image
    (B, Hp, Wp) instead of shared. Returns (B, H, W) complex. This is ``MultiSliceModel(...,
    obliquity="per_source")`` for ``model``'s optics and window.
    """
    from .forward import MultiSliceModel

    corrected = MultiSliceModel(model.optics, model.plan, device=model.device, dtype=model.dtype, obliquity="per_source")
    return corrected.camera_field(delta_n, sources_um)


def secant_screen_camera_field(model, delta_n: torch.Tensor, sources_um: torch.Tensor) -> torch.Tensor:
    """Proposal: the multi-slice model with each screen's scattered part weighted by ``1/cos θ`` of its direction.

    First-order (Born) scattering from a slab of thickness Δz carries the factor ``i·(2π/λ)·Δz·Δn / cos θ_out``,
    θ_out the direction of the scattered plane wave (``cos θ = λ·qz/n_b``); the thin screen omits ``1/cos θ_out``.
    Here a slice's step is ``u ← u + F⁻¹[sec(f)·F[(t − 1)·u]]`` with ``t`` the usual screen: exact to first order
    in Δn for any object, and for a uniform slab its error falls as 1/n_slices. Cost: one more FFT pair per slice.
    Returns (B, H, W) complex.
    """
    from .propagation import axial_frequency_offset

    k = model.kernels()
    dn = model.pad_volume(delta_n)
    f2 = k.fy * k.fy + k.fx * k.fx
    offset, propagating = axial_frequency_offset(f2, model.optics.n_background, k.wavelength_um)
    k_b = model.optics.n_background / k.wavelength_um
    max_sec = 1.0 / math.sqrt(1.0 - 0.98**2)
    sec = torch.where(propagating, torch.clamp(k_b / (offset + k_b), max=max_sec), torch.zeros_like(f2))
    u = torch.fft.ifft2(model.source_spectrum(sources_um.to(model.device, model.dtype), k))
    for i in range(dn.shape[0]):
        if i:
            u = torch.fft.ifft2(torch.fft.fft2(u) * k.slice_kernel)
        t = phase_screen(dn[i], k.slice_spacing_um, k.wavelength_um) - 1.0
        u = u + torch.fft.ifft2(torch.fft.fft2(t * u) * sec)
    u = torch.fft.ifft2(torch.fft.fft2(u) * k.exit_kernel)
    return model.crop(u)
