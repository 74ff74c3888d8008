"""Fused CUDA kernel (Triton) for one screen's adjoint in :mod:`napari_fdt.model.slice_loop`.

In plain torch the adjoint of ``u = P·v`` costs five passes over the batch of fields (``g·conj(u)``,
its imaginary part, the batch sum, ``g·conj(P)``, ``u·conj(P)``); this kernel reads ``g`` and ``u``
once, computes ``P = exp(i·φ)`` in registers, and writes ``g·conj(P)``, optionally ``u·conj(P)``, and
``Σ_b Im(g·conj(u))``. complex64 only, CUDA only; :func:`available` says whether it can run.
Checked against the torch version in ``benchmarks/gpu_checks.py`` (no GPU in CI).
"""

from __future__ import annotations

import functools

import torch

__all__ = ["available", "adjoint_screen"]


@functools.lru_cache(maxsize=1)
def available() -> bool:
    """True when Triton imports and a CUDA device is present."""
    if not torch.cuda.is_available():
        return False
    try:
        import triton  # noqa: F401
        import triton.language  # noqa: F401
    except Exception:
        return False
    return _kernel() is not None


@functools.lru_cache(maxsize=1)
def _kernel():
    import triton
    import triton.language as tl

    @triton.jit
    def adjoint_screen_kernel(g_ptr, u_ptr, phi_ptr, v_ptr, gphi_ptr, n_batch, n_pix,
                              WRITE_V: tl.constexpr, BLOCK: tl.constexpr):
        pid = tl.program_id(0)
        offs = pid * BLOCK + tl.arange(0, BLOCK)
        mask = offs < n_pix
        phi = tl.load(phi_ptr + offs, mask=mask, other=0.0)
        c = tl.cos(phi)
        s = tl.sin(phi)  # conj(P) = c − i·s
        acc = tl.zeros((BLOCK,), dtype=tl.float32)
        for b in range(n_batch):
            base = (b * n_pix + offs).to(tl.int64) * 2
            gr = tl.load(g_ptr + base, mask=mask, other=0.0)
            gi = tl.load(g_ptr + base + 1, mask=mask, other=0.0)
            ur = tl.load(u_ptr + base, mask=mask, other=0.0)
            ui = tl.load(u_ptr + base + 1, mask=mask, other=0.0)
            acc += gi * ur - gr * ui
            tl.store(g_ptr + base, gr * c + gi * s, mask=mask)
            tl.store(g_ptr + base + 1, gi * c - gr * s, mask=mask)
            if WRITE_V:
                tl.store(v_ptr + base, ur * c + ui * s, mask=mask)
                tl.store(v_ptr + base + 1, ui * c - ur * s, mask=mask)
        tl.store(gphi_ptr + offs, acc, mask=mask)

    return adjoint_screen_kernel


def adjoint_screen(g: torch.Tensor, u: torch.Tensor, phi_k: torch.Tensor, v_out: torch.Tensor | None) -> torch.Tensor:
    """Same contract as ``slice_loop._adjoint_screen``: returns Σ_b Im(g·conj(u)); g ← g·conj(P); v_out ← u·conj(P)."""
    import triton

    if not (g.is_contiguous() and u.is_contiguous()):
        raise ValueError("adjoint_screen needs contiguous fields")
    b = g.shape[0]
    n_pix = g.shape[-1] * g.shape[-2]
    phi = phi_k.contiguous()
    grad_phi = torch.empty(phi.shape, dtype=torch.float32, device=g.device)
    gr = torch.view_as_real(g)
    ur = torch.view_as_real(u)
    vr = torch.view_as_real(v_out) if v_out is not None else gr
    block = 1024
    grid = (triton.cdiv(n_pix, block),)
    _kernel()[grid](gr, ur, phi, vr, grad_phi, b, n_pix, WRITE_V=v_out is not None, BLOCK=block, num_warps=8)
    return grad_phi
