"""The slice loop's FFTs as small DFT-matrix products (a two-level "four-step" FFT), in plain torch (issue 16, item 2).

A length-N DFT with N = N1·N2 is, for ``n = N2·n1 + n2`` and ``k = k1 + N1·k2``,

    X[k1 + N1·k2] = Σ_{n2} W_N^{n2·k1} · W_{N2}^{n2·k2} · Σ_{n1} W_{N1}^{n1·k1} · x[N2·n1 + n2]:

a product with the N1×N1 DFT matrix, a twiddle factor, a product with the N2×N2 one. In 2D both axes go together:
two small products, one twiddle pass, two small products. The spectrum is left in this *digit order*
``[k1_h, k2_h, k1_w, k2_w]``; the propagator is stored in the same order (:meth:`DftPlan.permute`), and the inverse
transform reads it, so no transposition is ever made. Work per point is N1 + N2 complex multiply-adds per axis
(48 at 512 = 16·32) against ~log2 N for an FFT, but it runs as dense matrix products, which GPUs' tensor units do
at many times their FFT rate: this is the form in which a fused GPU kernel would apply the screen on load and the
propagator on store. Here it is the reference for such a kernel, differentiable by autograd and checked against
the FFT loop (``tests/test_dft_loop.py``); ``benchmarks/dft_loop_speed.py`` times it against ``torch.fft``.
Not used by the models (on the CPU it is slower than the FFT, ``docs/benchmarks.md``), so it lives with the benchmarks;
the digit order it shares with the fused CUDA loop is :mod:`napari_fdt.model.fused_loop`'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from napari_fdt.model.fused_loop import digit_index, split_factors

__all__ = ["DftPlan", "split_factors", "digit_index", "dft_slice_loop"]


def _dft(n: int, sign: float, dtype: torch.dtype, device) -> torch.Tensor:
    j = torch.arange(n, dtype=torch.float64)
    ang = sign * 2 * math.pi * torch.outer(j, j) / n
    return torch.polar(torch.ones_like(ang), ang).to(dtype=dtype, device=device)


@dataclass
class _Axis:
    n1: int
    n2: int
    f1: torch.Tensor  # (n1, n1) forward DFT
    f2: torch.Tensor  # (n2, n2)
    twiddle: torch.Tensor  # (n1, n2): W_N^{k1·n2}

    @classmethod
    def build(cls, n: int, dtype: torch.dtype, device) -> _Axis:
        n1, n2 = split_factors(n)
        k1 = torch.arange(n1, dtype=torch.float64)[:, None]
        m2 = torch.arange(n2, dtype=torch.float64)[None, :]
        ang = -2 * math.pi * k1 * m2 / n
        tw = torch.polar(torch.ones_like(ang), ang).to(dtype=dtype, device=device)
        return cls(n1, n2, _dft(n1, -1.0, dtype, device), _dft(n2, -1.0, dtype, device), tw)

    def digit_index(self) -> torch.Tensor:
        """(n1, n2) natural frequency index ``k1 + n1·k2`` of each digit-order position [k1, k2]."""
        return digit_index(self.n1, self.n2)


class DftPlan:
    """Matrices for 2D transforms of (..., H, W) complex fields (complex64 or complex128)."""

    def __init__(self, shape: tuple[int, int], *, dtype: torch.dtype = torch.complex64, device="cpu") -> None:
        self.shape = tuple(int(s) for s in shape)
        self.h = _Axis.build(self.shape[0], dtype, device)
        self.w = _Axis.build(self.shape[1], dtype, device)
        # both axes' twiddles as one (h1, h2, w1, w2) factor, applied in one pass
        self.twiddle = self.h.twiddle[:, :, None, None] * self.w.twiddle[None, None, :, :]
        self.twiddle_conj = self.twiddle.conj().resolve_conj()
        self.f1h_conj, self.f2h_conj = self.h.f1.conj().resolve_conj(), self.h.f2.conj().resolve_conj()
        self.f1w_conj, self.f2w_conj = self.w.f1.conj().resolve_conj(), self.w.f2.conj().resolve_conj()

    def _split(self, u: torch.Tensor) -> torch.Tensor:
        return u.reshape(*u.shape[:-2], self.h.n1, self.h.n2, self.w.n1, self.w.n2)

    def fft2(self, u: torch.Tensor) -> torch.Tensor:
        """Unnormalised 2D DFT of (B, H, W), returned in digit order as (B, h1, h2, w1, w2)."""
        x = self._split(u)
        a = torch.einsum("pa,bacde->bpcde", self.h.f1, x)
        a = torch.einsum("qd,bpcde->bpcqe", self.w.f1, a)
        a = a * self.twiddle
        s = torch.einsum("bpcqe,cr->bprqe", a, self.h.f2)
        return torch.einsum("bprqe,es->bprqs", s, self.w.f2)

    def ifft2(self, spec: torch.Tensor) -> torch.Tensor:
        """Unnormalised inverse of :meth:`fft2` (``torch.fft.ifft2(·, norm="forward")``): digit order → (B, H, W)."""
        c = torch.einsum("bprqs,rn->bpnqs", spec, self.f2h_conj)
        c = torch.einsum("bpnqs,sm->bpnqm", c, self.f2w_conj)
        c = c * self.twiddle_conj
        x = torch.einsum("ap,bpnqm->banqm", self.f1h_conj, c)
        x = torch.einsum("dq,banqm->bandm", self.f1w_conj, x)
        return x.reshape(*x.shape[:-4], *self.shape)

    def permute(self, kernel: torch.Tensor) -> torch.Tensor:
        """A (H, W) array in natural frequency order (as ``torch.fft.fft2`` returns) → digit order (h1, h2, w1, w2)."""
        ih = self.h.digit_index().to(kernel.device)
        iw = self.w.digit_index().to(kernel.device)
        return kernel[ih[:, :, None, None], iw[None, None, :, :]]


def dft_slice_loop(v0: torch.Tensor, phi: torch.Tensor, kernel: torch.Tensor, plan: DftPlan | None = None) -> torch.Tensor:
    """``u_{N−1}`` of :func:`napari_fdt.model.slice_loop.slice_loop` with the FFTs as DFT-matrix products.

    ``v0`` (B, H, W) complex, ``phi`` (N, H, W) screen phases (radians), ``kernel`` (H, W) the one-slice propagator
    in ``fft2`` order. Differentiable by plain autograd in all three.
    """
    plan = plan or DftPlan(tuple(v0.shape[-2:]), dtype=v0.dtype, device=v0.device)
    kp = plan.permute(kernel) / (kernel.shape[-1] * kernel.shape[-2])
    screens = torch.polar(torch.ones_like(phi), phi)
    u = v0 * screens[0]
    for k in range(1, phi.shape[0]):
        u = plan.ifft2(plan.fft2(u) * kp) * screens[k]
    return u
