"""The naive reference: a plain-autograd eager multi-slice step, kept here only to measure speed-ups.

One training step as a first implementation writes it: every slice ``u ← ifft2(fft2(u)·K)·exp(iφ_k)``
through PyTorch autograd, then the exit propagation, the intensity, an L2 loss and ``backward()``.
No padding, no kernel caching tricks, nothing fused. ``benchmarks/step_speed.py`` times it beside the
package's step on the same inputs, in the same process, so each speed-up is a measured ratio.
"""

from __future__ import annotations

import torch


def naive_loop(v0: torch.Tensor, phi: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """The slice loop in plain autograd: screens of phase ``phi`` (N, H, W), propagator ``kernel`` between them."""
    u = v0
    for k in range(phi.shape[0]):
        if k:
            u = torch.fft.ifft2(torch.fft.fft2(u) * kernel)
        u = u * torch.exp(1j * phi[k])
    return u


def naive_step(v0: torch.Tensor, delta_n: torch.Tensor, kernel: torch.Tensor, exit_kernel: torch.Tensor,
               target: torch.Tensor, phase_per_dn: float) -> torch.Tensor:
    """Loss of one batch, differentiable in ``delta_n`` (N, H, W); ``v0`` (B, H, W) the incoming fields."""
    u = naive_loop(v0, phase_per_dn * delta_n, kernel)
    u = torch.fft.ifft2(torch.fft.fft2(u) * exit_kernel)
    intensity = u.real ** 2 + u.imag ** 2
    return ((intensity - target) ** 2).mean()
