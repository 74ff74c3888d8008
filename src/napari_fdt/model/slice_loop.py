"""The multi-slice loop as one autograd Function with a hand-written adjoint.

Plain autograd keeps several complex fields per slice and per image and runs many small elementwise
kernels in its backward pass. Here the loop

    u_0 = P_0 · v_0,    u_k = P_k · ifft2(K · fft2(u_{k-1})),   k = 1 … N−1,    P_k = exp(i·φ_k)

(``v_0`` the field arriving at the first screen, ``φ_k`` the phase of screen k in radians, ``K`` the
propagator over one slice) returns ``u_{N−1}``; its backward pass is written out by hand, in one of
three modes that trade memory for work:

``"stored"``
    keeps every ``u_k``: N fields per image, the least work (one forward, one adjoint propagation).
``"reversible"``
    keeps only ``u_{N−1}`` and re-propagates it backwards with the conjugate kernel while it forms the
    adjoint (both in one batched FFT): memory independent of N, exact when ``|K| = 1`` everywhere (no
    evanescent frequency on the grid, ``docs/physics.md``); about 1.5× the work of ``"stored"``.
``"checkpoint"``
    keeps ``u_k`` every ``s ≈ √N`` slices and recomputes each segment during the backward pass:
    ``≈ 2√N`` fields, valid for any kernel, about 1.5× the work of ``"stored"``.

:func:`choose_mode` picks the cheapest mode whose memory fits. Gradients (PyTorch's convention for
complex tensors) flow to ``v_0``, ``φ`` and ``K``; they are checked against autograd in
``tests/test_slice_loop.py``. On CUDA, the per-slice adjoint arithmetic runs in one Triton kernel
(one pass instead of torch's five) when Triton is importable (:mod:`napari_fdt.model._triton_slice`); elsewhere
in plain torch.
"""

from __future__ import annotations

import math

import torch

from napari_fdt.physics.propagation import phasor

__all__ = ["slice_loop", "loop_forward", "choose_mode", "leanest_mode", "is_unitary", "loop_bytes", "MODES"]

MODES = ("stored", "reversible", "checkpoint")

#: Relative tolerance on |K| = 1 for the reversible mode (float32 kernels are unitary to ~1e-7).
_UNITARY_TOL = 1e-5


def is_unitary(kernel: torch.Tensor) -> bool:
    """True when every entry of the propagation kernel has modulus 1 (within 1e-5)."""
    return bool(((kernel.detach().abs() - 1.0).abs() <= _UNITARY_TOL).all())


def _segment(n_slices: int) -> int:
    return max(1, int(math.ceil(math.sqrt(n_slices))))


def loop_bytes(mode: str, field_bytes: int, n_slices: int, batch: int) -> int:
    """Peak bytes the loop keeps for one forward + backward, beyond its inputs.

    ``field_bytes`` is one image's field (Hp·Wp·8 for complex64). Counts the saved fields, the working
    fields of the backward pass (adjoint, FFT output and input, stacked pair in reversible mode) and a
    margin for cuFFT's work area; measured peaks are in ``docs/benchmarks.md``.
    """
    per_batch = field_bytes * batch
    work = 6 * per_batch  # adjoint + FFT in/out (+ pair buffers), cuFFT work area
    if mode == "stored":
        return n_slices * per_batch + work
    if mode == "reversible":
        return 2 * per_batch + work
    if mode == "checkpoint":
        s = _segment(n_slices)
        return (int(math.ceil(n_slices / s)) + s) * per_batch + work
    raise ValueError(f"unknown mode {mode!r}; one of {MODES}")


def leanest_mode(unitary: bool) -> str:
    """The backward mode that needs least memory: reversible for a unitary propagator, else checkpoint."""
    return "reversible" if unitary else "checkpoint"


def choose_mode(field_bytes: int, n_slices: int, batch: int, unitary: bool, budget_bytes: int | None) -> str:
    """The cheapest backward mode that fits ``budget_bytes`` (None: no limit → ``"stored"``).

    ``unitary``: whether the propagator has modulus 1 everywhere (:func:`is_unitary`). Order of
    preference: stored (least work), then :func:`leanest_mode`; when none fits, the caller's memory check
    has refused the run earlier.
    """
    if budget_bytes is None or loop_bytes("stored", field_bytes, n_slices, batch) <= budget_bytes:
        return "stored"
    return leanest_mode(unitary)


# -- per-slice arithmetic (torch fallback; the Triton kernel does the same in one pass) ------------
def _screen(phi_k: torch.Tensor) -> torch.Tensor:
    return phasor(phi_k)


def _adjoint_screen(g: torch.Tensor, u: torch.Tensor, phi_k: torch.Tensor, v_out: torch.Tensor | None,
                    grad_out: torch.Tensor | None = None) -> torch.Tensor:
    """One screen's adjoint, in place: returns ``Σ_b Im(g·conj(u))`` (the φ_k gradient, (Hp, Wp); written into
    ``grad_out`` when given, a contiguous (Hp, Wp) float tensor); sets ``g ← g·conj(P_k)`` and, if ``v_out`` is given,
    ``v_out ← u·conj(P_k)`` (the field before the screen).
    """
    if g.is_cuda and g.dtype == torch.complex64:
        from napari_fdt.model import _triton_slice

        if _triton_slice.available():
            return _triton_slice.adjoint_screen(g, u, phi_k, v_out, out=grad_out)
    grad_phi = torch.sum(g.imag * u.real - g.real * u.imag, 0, out=grad_out)
    conj_p = _screen(-phi_k)
    g.mul_(conj_p)
    if v_out is not None:
        torch.mul(u, conj_p, out=v_out)
    return grad_phi


def _scaled(kernel: torch.Tensor) -> torch.Tensor:
    """``K / (Hp·Wp)``: with it, ``ifft2(K·fft2(u)) = ifft2(fft2(u)·K/N, norm="forward")``, which saves
    the separate scaling pass PyTorch's normalised inverse FFT makes over the whole batch."""
    return kernel / (kernel.shape[-1] * kernel.shape[-2])


def _propagate(u: torch.Tensor, scaled_kernel: torch.Tensor) -> torch.Tensor:
    """``ifft2(K·fft2(u))`` over the last two axes, given ``K/N`` (:func:`_scaled`); a new tensor."""
    spec = torch.fft.fft2(u)
    spec.mul_(scaled_kernel)
    return torch.fft.ifft2(spec, norm="forward")


def _forward(v0: torch.Tensor, phi: torch.Tensor, kernel: torch.Tensor, keep: list[int] | None) -> tuple[torch.Tensor, dict[int, torch.Tensor]]:
    """Run the loop; return ``u_{N−1}`` and the fields ``u_k`` for k in ``keep`` (all if keep is None).

    With every field kept (the stored mode: N fields per image held anyway) the N screens are made in one call, one
    kernel instead of N on a GPU, where an iteration is bound by its kernel launches; otherwise one at a time, so that
    the memory-lean modes hold one screen, not N.
    """
    n = phi.shape[0]
    kept: dict[int, torch.Tensor] = {}
    screens = _screen(phi) if keep is None else None
    u = v0 * (screens[0] if screens is not None else _screen(phi[0]))
    if keep is None or 0 in keep:
        kept[0] = u
    scaled = _scaled(kernel)
    for k in range(1, n):
        u = _propagate(u, scaled)
        u.mul_(screens[k] if screens is not None else _screen(phi[k]))
        if keep is None or k in keep:
            kept[k] = u
    return u, kept


def loop_forward(v0: torch.Tensor, phi: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """``u_{N−1}`` without gradients, one field alive at a time (inference)."""
    return _forward(v0, phi, kernel, [])[0]


class _SliceLoop(torch.autograd.Function):
    @staticmethod
    def forward(ctx, v0: torch.Tensor, phi: torch.Tensor, kernel: torch.Tensor, mode: str) -> torch.Tensor:  # type: ignore[override]
        n = phi.shape[0]
        if mode == "stored":
            keep = None
        elif mode == "reversible":
            keep = []
        elif mode == "checkpoint":
            keep = list(range(0, n, _segment(n)))
        else:
            raise ValueError(f"unknown backward mode {mode!r}; one of {MODES}")
        out, kept = _forward(v0, phi, kernel, keep)
        ctx.mode = mode
        ctx.kept_index = sorted(kept)
        ctx.save_for_backward(phi, kernel, out, *(kept[i] for i in ctx.kept_index))
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):  # type: ignore[override]
        phi, kernel, out, *kept_list = ctx.saved_tensors
        kept = dict(zip(ctx.kept_index, kept_list))
        need_v0, need_phi, need_k = ctx.needs_input_grad[:3]
        n = phi.shape[0]
        npix = kernel.shape[-1] * kernel.shape[-2]
        g = grad_out.clone(memory_format=torch.contiguous_format)  # the Triton kernel needs contiguous fields
        grad_phi = torch.empty(phi.shape, dtype=phi.dtype, device=phi.device) if need_phi else None  # contiguous: rows are out= targets
        grad_k = torch.zeros_like(kernel) if need_k else None
        conj_k = _scaled(kernel.conj())
        scaled = _scaled(kernel)
        mode = ctx.mode
        seg = _segment(n)
        cache: dict[int, torch.Tensor] = {}

        def _recomputed(j: int, keep_in_cache: bool = False) -> torch.Tensor:
            """u_j in checkpoint mode: recompute its segment (up to j) from the segment's first field."""
            if j not in cache:
                start = (j // seg) * seg
                cache.clear()
                u_s = kept[start]
                cache[start] = u_s
                for i in range(start + 1, j + 1):
                    u_s = _propagate(u_s, scaled)
                    u_s.mul_(_screen(phi[i]))
                    cache[i] = u_s
            return cache[j] if keep_in_cache else cache.pop(j)

        if mode == "reversible":
            pair = torch.empty((2, *g.shape), dtype=g.dtype, device=g.device)
            pair[1].copy_(g)
            g = pair[1]
            u = out
        for k in range(n - 1, -1, -1):
            if mode == "reversible":
                # u holds u_k; write v_k = conj(P_k)·u_k into pair[0] and g·conj(P_k) into pair[1].
                _adjoint_screen(g, u, phi[k], pair[0], None if grad_phi is None else grad_phi[k])
                if k == 0:
                    g = pair[1]
                    break
                spec = torch.fft.fft2(pair)
                if grad_k is not None:
                    # conj(fft2(u_{k−1})) = K·conj(fft2(v_k)); adjoint of ifft2 is fft2/Hp·Wp.
                    grad_k += kernel * (spec[0].conj() * spec[1]).sum(0) / npix
                spec.mul_(conj_k)
                pair = torch.fft.ifft2(spec, norm="forward")
                u, g = pair[0], pair[1]
                continue
            u_k = kept[k] if mode == "stored" else _recomputed(k)
            _adjoint_screen(g, u_k, phi[k], None, None if grad_phi is None else grad_phi[k])
            del u_k
            if k == 0:
                break
            spec = torch.fft.fft2(g)
            if grad_k is not None:
                prev = kept[k - 1] if mode == "stored" else _recomputed(k - 1, keep_in_cache=True)
                grad_k += (torch.fft.fft2(prev).conj() * spec).sum(0) / npix
                del prev
            spec.mul_(conj_k)
            g = torch.fft.ifft2(spec, norm="forward")
        return (g if need_v0 else None), grad_phi, grad_k, None


def slice_loop(v0: torch.Tensor, phi: torch.Tensor, kernel: torch.Tensor, mode: str = "stored", *, check: bool = True) -> torch.Tensor:
    """``u_{N−1}`` of the loop above, differentiable in ``v0``, ``phi`` and ``kernel``.

    Parameters
    ----------
    v0: (B, Hp, Wp) complex, the field arriving at the first screen.
    phi: (N, Hp, Wp) real, phase of each screen in radians (``2π/λ·Δz·Δn``).
    kernel: (Hp, Wp) complex, the propagator over one slice (``fft2`` frequency order).
    mode: ``"stored"``, ``"reversible"`` or ``"checkpoint"`` (see the module docstring).
    check: verify that the kernel is unitary for ``"reversible"`` (one device synchronisation; callers
        that know it, like :class:`~napari_fdt.model.forward.MultiSliceModel`, pass False).
    """
    if mode not in MODES:
        raise ValueError(f"unknown backward mode {mode!r}; one of {MODES}")
    if phi.ndim != 3 or v0.ndim != 3 or tuple(v0.shape[-2:]) != tuple(phi.shape[-2:]) or tuple(kernel.shape) != tuple(phi.shape[-2:]):
        raise ValueError(f"shapes do not match: v0 {tuple(v0.shape)}, phi {tuple(phi.shape)}, kernel {tuple(kernel.shape)}")
    if check and mode == "reversible" and not is_unitary(kernel):
        raise ValueError("the reversible mode needs a kernel of modulus 1 everywhere (no evanescent or damped "
                         "frequencies); use 'stored' or 'checkpoint'")
    return _SliceLoop.apply(v0, phi, kernel, mode)
