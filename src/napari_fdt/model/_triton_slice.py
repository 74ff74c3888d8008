"""One CUDA kernel (Triton) for one screen's adjoint in :mod:`napari_fdt.model.slice_loop`.

In plain torch the adjoint of ``u = P·v`` costs five passes over the batch of fields (``g·conj(u)``,
its imaginary part, the batch sum, ``g·conj(P)``, ``u·conj(P)``); this kernel reads ``g`` and ``u``
once, computes ``P = exp(i·φ)`` in registers, and writes ``g·conj(P)``, optionally ``u·conj(P)``, and
``Σ_b Im(g·conj(u))``. complex64 only, CUDA only; :func:`available` says whether it can run.
Checked against the torch version in ``benchmarks/gpu_checks.py`` on a GPU and, through Triton's CPU interpreter,
in ``tests/test_triton_slice.py``. The kernel itself is in :mod:`napari_fdt.model._triton_adjoint` (the one module
that imports Triton at its top).

Triton is imported only where it could run: on a CUDA machine, or by a caller asking for the interpreter. Importing
it in a process where napari has loaded Mesa's OpenGL (its libLLVM) crashes, so a CPU-only model never touches it
(``tests/test_triton_slice.py`` checks that in a fresh process).
"""

from __future__ import annotations

import functools

import torch

__all__ = ["available", "triton_importable", "adjoint_screen"]


@functools.lru_cache(maxsize=1)
def triton_importable() -> bool:
    """True when Triton imports (this imports it: call it only where Triton could run, see the module's note)."""
    try:
        import triton  # noqa: F401
        import triton.language  # noqa: F401
    except Exception:
        return False
    return True


@functools.lru_cache(maxsize=1)  # asked once per slice of every backward pass on CUDA
def available() -> bool:
    """True when a CUDA device is present and Triton imports (Triton is not imported without CUDA)."""
    return torch.cuda.is_available() and triton_importable()


@functools.lru_cache(maxsize=2)
def _kernel(interpret: bool = False):
    from napari_fdt.model import _triton_adjoint

    return _triton_adjoint.build_adjoint_screen(interpret)


def adjoint_screen(g: torch.Tensor, u: torch.Tensor, phi_k: torch.Tensor, v_out: torch.Tensor | None,
                   *, out: torch.Tensor | None = None, interpret: bool = False) -> torch.Tensor:
    """Same contract as ``slice_loop._adjoint_screen``: returns Σ_b Im(g·conj(u)); g ← g·conj(P); v_out ← u·conj(P).

    ``out``: a contiguous float32 tensor of φ's shape to write Σ_b Im(g·conj(u)) into (one allocation less per
    screen). ``interpret``: run CPU tensors through Triton's interpreter (tests).
    """
    import triton

    if not (g.is_contiguous() and u.is_contiguous()):
        raise ValueError("adjoint_screen needs contiguous fields")
    b = g.shape[0]
    n_pix = g.shape[-1] * g.shape[-2]
    phi = phi_k.contiguous()
    if out is not None and not (out.is_contiguous() and out.dtype == torch.float32 and out.shape == phi.shape):
        raise ValueError("adjoint_screen's out must be a contiguous float32 tensor of phi's shape")
    grad_phi = torch.empty(phi.shape, dtype=torch.float32, device=g.device) if out is None else out
    gr = torch.view_as_real(g)
    ur = torch.view_as_real(u)
    vr = torch.view_as_real(v_out) if v_out is not None else gr
    block = 1024
    grid = (triton.cdiv(n_pix, block),)
    _kernel(interpret)[grid](gr, ur, phi, vr, grad_phi, b, n_pix, WRITE_V=v_out is not None, BLOCK=block, num_warps=8)
    return grad_phi
