"""Triton kernel of one screen's adjoint in the slice loop (:mod:`napari_fdt.model._triton_slice`); imported only
when Triton is (:func:`napari_fdt.model._triton_slice.available`, or a test running Triton's CPU interpreter).

``_adjoint_screen`` — one program per block of BLOCK pixels of a (B, H, W) complex64 batch stored as interleaved
float32 (``torch.view_as_real``): reads ``g`` and ``u`` once per image, computes ``P = exp(i·φ)`` in registers,
writes ``g·conj(P)`` in place, optionally ``u·conj(P)``, and the batch sum ``Σ_b Im(g·conj(u))``.

The kernel calls no function decorated with ``triton.jit`` (``tl.zeros`` is one): Triton's interpreter runs it
through ``InterpretedFunction``, which cannot call them.
"""

from __future__ import annotations

import triton
import triton.language as tl


def _adjoint_screen(g_ptr, u_ptr, phi_ptr, v_ptr, gphi_ptr, n_batch, n_pix,
                    WRITE_V: tl.constexpr, BLOCK: tl.constexpr):
    pid = tl.program_id(0)
    offs = pid * BLOCK + tl.arange(0, BLOCK)
    mask = offs < n_pix
    phi = tl.load(phi_ptr + offs, mask=mask, other=0.0)
    c = tl.cos(phi)
    s = tl.sin(phi)  # conj(P) = c − i·s
    acc = tl.full((BLOCK,), 0.0, tl.float32)  # tl.full, a builtin: tl.zeros is a jit function the interpreter cannot call
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


def build_adjoint_screen(interpret: bool):
    """The one-screen adjoint kernel of :mod:`napari_fdt.model._triton_slice` (compiled, or interpreted)."""
    if interpret:
        from triton.runtime.interpreter import InterpretedFunction

        return InterpretedFunction(_adjoint_screen)
    return triton.jit(_adjoint_screen)
