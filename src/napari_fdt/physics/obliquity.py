"""Obliquity of the thin phase screen: the exact phase of a uniform slab, against which the screens are measured.

A thin screen gives every plane-wave component crossing a slab of thickness T and contrast Δn the same phase
``2π·T·Δn/λ`` (:func:`napari_fdt.physics.propagation.screen_phase`). The exact (reflection-free) slab phase of the
component of lateral frequency f is

    φ_exact(f) = 2π·T·(sqrt((n_b + Δn)²/λ² − f²) − sqrt(n_b²/λ² − f²)) = 2π·T·Δn/(λ·cos θ) + O(Δn²),

with ``sin θ = λ·f/n_b``: the screen under-counts the path of oblique light by ``1/cos θ − 1`` (6 % at
NA 0.45 in water, 41 % at 0.94). Splitting the slab into more slices does not help: for a laterally uniform
slab the screens commute with the propagation, and the model's phase is ``2π·T·Δn/λ`` whatever the slice count
(``benchmarks/obliquity.py``, ``docs/physics.md`` §6). The per-source correction that removes most of it is the
model's ``MultiSliceModel(..., obliquity="per_source")`` (:func:`napari_fdt.model.forward.ray_secant`).
"""

from __future__ import annotations

import math

import torch

__all__ = ["slab_phase_exact", "obliquity_error"]


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


def obliquity_error(sin_theta, delta_n: float, n_background: float):
    """``φ_exact/φ_screen − 1`` at the angle ``sin θ`` in the background (exact in Δn; → ``1/cos θ − 1`` as Δn → 0)."""
    lib = torch if isinstance(sin_theta, torch.Tensor) else __import__("numpy")
    s2 = sin_theta * sin_theta
    n0, n1 = n_background, n_background + delta_n
    # (sqrt(n1² − n0²s²) − n0·cos θ)/Δn − 1, λ and T cancel
    return (n1 * n1 - n0 * n0) / (delta_n * (lib.sqrt(n1 * n1 - n0 * n0 * s2) + n0 * lib.sqrt(1.0 - s2))) - 1.0


