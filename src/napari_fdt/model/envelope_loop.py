"""The envelope model's slice loop for all sources at once, as one autograd Function with a hand-written adjoint.

Per source b (batch axis) and slice k the loop is

    u_0 = P_0,    u_k = P_k · F⁻¹(K_{k−1} · F(u_{k−1})),  k = 1 … N−1,    out = F⁻¹(K_{N−1} · F(u_{N−1}))

with ``P`` (B, N, h, w) the screens, ``K`` (B, N, h, w) the step kernels (already divided by h·w, so that ``F⁻¹``
is the unnormalised inverse FFT, ``norm="forward"``) and ``F`` the unnormalised 2D FFT. Unlike
:mod:`napari_fdt.model.slice_loop`, screens and kernels differ per source (the envelope's p-grid and heights are
per source). Autograd through this loop records ~30 operations per slice for the backward pass, among them a
zero-filled (B, N, h, w) gradient per indexed slice; the adjoint here runs two FFTs, two products and two
copies per slice, and finishes the gradients of ``P`` and ``K`` with one product each over all slices.

Gradients follow PyTorch's convention for complex tensors (``grad_x = Aᴴ·grad_y`` for ``y = A·x``); they are
checked against autograd in ``tests/test_envelope.py``.
"""

from __future__ import annotations

import torch

__all__ = ["envelope_loop"]


class _EnvelopeLoop(torch.autograd.Function):
    @staticmethod
    def forward(ctx, screens: torch.Tensor, kernels: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        n = screens.shape[1]
        need_k = ctx.needs_input_grad[1]
        # spectra[:, k] = F(u_k) (the gradient of K_k needs it); fields[:, k] = F⁻¹(K_{k−1}·F(u_{k−1})) = u_k·conj(P_k)
        spectra = torch.empty_like(kernels) if need_k else None
        fields = torch.empty_like(screens)
        u = screens[:, 0]
        for k in range(1, n + 1):
            s = torch.fft.fft2(u)
            if spectra is not None:
                spectra[:, k - 1] = s
            s.mul_(kernels[:, k - 1])
            w = torch.fft.ifft2(s, norm="forward")
            if k == n:
                u = w
                break
            fields[:, k] = w
            u = w * screens[:, k]
        fields[:, 0] = 1.0  # u_0 = P_0
        ctx.save_for_backward(screens, kernels, fields, *(() if spectra is None else (spectra,)))
        ctx.n = n
        return u

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):  # type: ignore[override]
        screens, kernels, fields, *spectra = ctx.saved_tensors
        n = ctx.n
        need_p, need_k = ctx.needs_input_grad[:2]
        # conjugates resolved once for all slices (a conj view would be materialised at every product)
        conj_k = kernels.conj().resolve_conj()
        conj_p = screens.conj().resolve_conj()
        # per slice, store the gradients of the products' outputs; multiply by the saved factors once at the end
        grad_p = torch.empty_like(screens)
        grad_k = torch.empty_like(kernels) if need_k else None
        g = grad_out
        for k in range(n, 0, -1):
            # g: gradient of w_k = F⁻¹(K_{k−1}·F(u_{k−1})) (k = n: of the output)
            gs = torch.fft.fft2(g)  # adjoint of the unnormalised inverse FFT
            if grad_k is not None:
                grad_k[:, k - 1] = gs
            gs.mul_(conj_k[:, k - 1])
            g = torch.fft.ifft2(gs, norm="forward")  # adjoint of the unnormalised FFT: gradient of u_{k−1}
            grad_p[:, k - 1] = g
            if k - 1 == 0:
                break
            g = g * conj_p[:, k - 1]  # gradient of w_{k−1}
        if grad_k is not None:
            grad_k.mul_(spectra[0].conj())
        if need_p:
            grad_p.mul_(fields.conj())
        return (grad_p if need_p else None), grad_k


def envelope_loop(screens: torch.Tensor, kernels: torch.Tensor) -> torch.Tensor:
    """Envelopes at the camera's focal plane, (B, h, w) complex, differentiable in ``screens`` and ``kernels``.

    ``screens``: (B, N, h, w) complex, ``exp(i·φ)`` of each source's screen at each slice; ``kernels``: (B, N, h, w)
    complex, the step after screen k (k < N−1: to screen k+1; k = N−1: to the focal plane) divided by h·w.
    """
    if screens.ndim != 4 or screens.shape != kernels.shape:
        raise ValueError(f"screens and kernels must both be (B, N, h, w), got {tuple(screens.shape)} and {tuple(kernels.shape)}")
    return _EnvelopeLoop.apply(screens, kernels)
