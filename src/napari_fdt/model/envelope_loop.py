"""The envelope model's slice loop for all sources at once, as one autograd Function with a hand-written adjoint.

Per slice k and source b (the arrays are slice-major, (N, B, h, w), so that each slice is contiguous) the loop is

    u_0 = P_0,    u_k = P_k · F⁻¹(K_{k−1} · F(u_{k−1})),  k = 1 … N−1,    out = F⁻¹(K_{N−1} · F(u_{N−1}))

with ``P`` (N, B, h, w) the screens, ``K`` (N, B, h, w) the step kernels (already divided by h·w, so that ``F⁻¹``
is the unnormalised inverse FFT, ``norm="forward"``) and ``F`` the unnormalised 2D FFT. Unlike
:mod:`napari_fdt.model.slice_loop`, screens and kernels differ per source (the envelope's p-grid and heights are
per source). Autograd through this loop records ~30 operations per slice for the backward pass, among them a
zero-filled (N, B, h, w) gradient per indexed slice; the adjoint here runs two FFTs, three products and one copy
per slice, and the gradient of the phases ``φ`` (``P = exp(i·φ)``) in three passes over all slices.

Gradients follow PyTorch's convention for complex tensors (``grad_x = Aᴴ·grad_y`` for ``y = A·x``); they are
checked against autograd in ``tests/test_envelope.py``.
"""

from __future__ import annotations

import math

import torch

from napari_fdt.physics.propagation import phasor

__all__ = ["envelope_loop", "step_kernels"]


class _EnvelopeLoop(torch.autograd.Function):
    @staticmethod
    def forward(ctx, phases: torch.Tensor, kernels: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        n = phases.shape[0]
        need_k = ctx.needs_input_grad[1]
        screens = phasor(phases)
        # conj_spectra[k] = conj(F(u_k)) (the gradient of K_k needs it); fields[k] = u_k (that of φ_k needs it)
        conj_spectra = torch.empty_like(kernels) if need_k else None
        fields = torch.empty_like(screens) if ctx.needs_input_grad[0] else None
        u = screens[0]
        for k in range(1, n + 1):
            if fields is not None:
                fields[k - 1] = u
            s = torch.fft.fft2(u)
            if conj_spectra is not None:
                conj_spectra[k - 1] = s.conj()  # the copy resolves the conjugation
            s.mul_(kernels[k - 1])
            u = torch.fft.ifft2(s, norm="forward")
            if k < n:
                u.mul_(screens[k])
        saved = [phases, kernels] + ([] if fields is None else [fields]) + ([] if conj_spectra is None else [conj_spectra])
        ctx.save_for_backward(*saved)
        ctx.n = n
        return u

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):  # type: ignore[override]
        need_phi, need_k = ctx.needs_input_grad[:2]
        phases, kernels, *rest = ctx.saved_tensors
        fields = rest.pop(0) if need_phi else None
        conj_spectra = rest.pop(0) if need_k else None
        n = ctx.n
        conj_k = kernels.conj().resolve_conj()  # once for all slices (a conj view would be materialised per product)
        conj_p = phasor(-phases)
        grads_u = torch.empty_like(fields) if need_phi else None  # gradient of every u_k, for φ at the end
        grad_k = torch.empty_like(kernels) if need_k else None
        g = grad_out
        for k in range(n, 0, -1):
            # g: gradient of w_k = F⁻¹(K_{k−1}·F(u_{k−1})) (k = n: of the output)
            gs = torch.fft.fft2(g)  # adjoint of the unnormalised inverse FFT
            if grad_k is not None:
                torch.mul(gs, conj_spectra[k - 1], out=grad_k[k - 1])
            gs.mul_(conj_k[k - 1])
            g = torch.fft.ifft2(gs, norm="forward")  # adjoint of the unnormalised FFT: gradient of u_{k−1}
            if grads_u is not None:
                grads_u[k - 1] = g
            if k == 1:
                break
            g.mul_(conj_p[k - 1])  # gradient of w_{k−1} (u_{k−1} = w_{k−1}·P_{k−1})
        grad_phi = None
        if need_phi:
            # u = w·exp(iφ): ∂L/∂φ = Im(g_u·conj(u)), as in napari_fdt.model.slice_loop
            grad_phi = grads_u.imag * fields.real - grads_u.real * fields.imag
        return grad_phi, grad_k


def envelope_loop(phases: torch.Tensor, kernels: torch.Tensor) -> torch.Tensor:
    """Envelopes at the camera's focal plane, (B, h, w) complex, differentiable in ``phases`` and ``kernels``.

    ``phases``: (N, B, h, w) real, the phase φ (radians) of each source's screen ``P = exp(i·φ)`` at each slice; ``kernels``: (N, B, h, w)
    complex, the step after screen k (k < N−1: to screen k+1; k = N−1: to the focal plane) divided by h·w.
    """
    if phases.ndim != 4 or phases.shape != kernels.shape:
        raise ValueError(f"phases and kernels must both be (N, B, h, w), got {tuple(phases.shape)} and {tuple(kernels.shape)}")
    return _EnvelopeLoop.apply(phases, kernels)


class _StepKernels(torch.autograd.Function):
    """``K = prop·exp(i·2π·Δz_eff·(q_z(f) − k))/N`` with ``f² = f_p²/h0²``, ``Δz_eff = (h1 − h0)·h0/h1``, ``k = n_b/λ``."""

    @staticmethod
    def forward(ctx, f2p: torch.Tensor, h0: torch.Tensor, h1: torch.Tensor, k: float, scale: float) -> torch.Tensor:  # type: ignore[override]
        inv_h02 = (h0 * h0).reciprocal()[:, :, None, None]
        f2 = f2p * inv_h02  # (N, B, h, w)
        dz_eff = ((h1 - h0) * h0 / h1)[:, :, None, None]
        prop = f2 < k * k
        # q_z − k written as −f²/(q_z + k) (full relative precision near the axis), 0 where evanescent
        offset = torch.clamp(k * k - f2, min=0.0).sqrt_().add_(k).reciprocal_().mul_(f2).mul_(prop).neg_()
        kernel = phasor(offset * (2 * math.pi) * dz_eff, prop.to(f2.dtype).mul_(scale))
        ctx.save_for_backward(f2p, h0, h1, kernel, offset)
        ctx.k = k
        return kernel

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        f2p, h0, h1, kernel, offset = ctx.saved_tensors
        k = ctx.k
        q = offset + k  # q_z where propagating (elsewhere K = 0 and so is every gradient below)
        # gradient of the phase θ (real): Re(conj(g)·i·K) = Im(g)·Re(K) − Re(g)·Im(K)
        g_theta = grad.imag * kernel.real - grad.real * kernel.imag
        two_pi = 2 * math.pi
        inv_h02 = (h0 * h0).reciprocal()
        dz_eff = (h1 - h0) * h0 / h1
        # θ = 2π·Δz_eff·(q − k): ∂θ/∂Δz_eff = 2π·(q − k) (0 where evanescent: g_theta is 0 there, |K| = 0)
        g_dz = (g_theta * offset).sum((-2, -1)) * two_pi
        # ∂θ/∂f² = 2π·Δz_eff·(−1/(2q)); q > 0 wherever K ≠ 0 except exactly at f = k (clamped like the autograd version)
        g_f2 = g_theta * (-math.pi) / torch.clamp(q, min=1e-30) * dz_eff[:, :, None, None]
        g_f2p = (g_f2 * inv_h02[:, :, None, None]).sum_to_size(f2p.shape) if ctx.needs_input_grad[0] else None
        # f² = f_p²/h0²: ∂f²/∂h0 = −2·f²/h0;  Δz_eff = h0 − h0²/h1: ∂/∂h0 = 1 − 2·h0/h1, ∂/∂h1 = h0²/h1²
        g_h0 = (g_f2 * f2p).sum((-2, -1)) * (-2.0 * inv_h02 / h0) + g_dz * (1.0 - 2.0 * h0 / h1)
        g_h1 = g_dz * (h0 * h0) / (h1 * h1)
        return g_f2p, g_h0, g_h1, None, None


def step_kernels(f2p: torch.Tensor, h0: torch.Tensor, h1: torch.Tensor, n_background: float, wavelength_um: float,
                 scale: float = 1.0) -> torch.Tensor:
    """Envelope step kernels of every step and source at once, (N, B, h, w) complex, times ``scale``.

    ``f2p`` (1, B, h, w): squared frequencies conjugate to the angular coordinate; ``h0``, ``h1`` (N, B): heights
    above the source where each step starts and ends, µm. The kernel is
    :meth:`napari_fdt.model.envelope.EnvelopeModel._kernel` (exact angular-spectrum step in the scaled frame), with a
    hand-written backward that reduces straight to the (N, B) heights and to ``f2p``: about half the full-size passes
    of autograd's. ``n_background`` and ``wavelength_um`` are plain numbers here (not differentiated).
    """
    return _StepKernels.apply(f2p, h0, h1, float(n_background) / float(wavelength_um), float(scale))
