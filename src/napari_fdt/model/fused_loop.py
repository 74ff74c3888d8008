"""The slice loop in two fused Triton kernels per slice (issue 16, item 2): FFTs as DFT-matrix products with the
screen and the propagator applied on load/store.

Same loop and gradient convention as :func:`napari_fdt.model.slice_loop.slice_loop` in its ``"stored"`` mode:

    u_0 = P_0·v_0,    u_k = P_k·ifft2(K·fft2(u_{k−1})),    P_k = exp(i·φ_k).

One slice step is two passes over the batch of fields instead of the FFT loop's two FFTs (each one or more
passes) and two elementwise passes (``docs/benchmarks.md``):

* ``inner`` (one program per pair of first digits): the second half of the DFT, the propagator, the first half
  of the inverse DFT and its twiddle, on an N2H × N2W tile held in registers;
* ``outer`` (one program per second digits): the last half of the inverse DFT, the screen of the next slice, the
  field written for the backward pass, the first half of the next DFT with its twiddle.

The adjoint is the same chain run backwards with conj(K) and −φ, the screen gradient ``Σ_b Im(g·conj(u_k))``
formed inside ``outer`` from the stored fields. The layout is the four-step transform's digit order
(:func:`digit_index`; its plain-torch reference is ``benchmarks/_dft_loop.py``), so the intermediates never leave
their places in memory (both kernels work in place on one buffer).

Where it runs: CUDA tensors with Triton (compiled), and CPU tensors through Triton's interpreter when
``interpret=True`` (numpy, slow: for tests). Sizes: any H and W whose factors (``split_factors``) are at most
:data:`MAX_FACTOR`; each factor's tile is padded to a power of two (at least 16 on CUDA, ``tl.dot``'s smallest
tile) and masked, so the 2·3·5-smooth windows of :func:`~napari_fdt.physics.grid.plan_grid` waste up to ~2×
per side in the small products (none for powers of two). complex64 only; the propagator is a constant (no
gradient to K). :func:`supports` says whether a case qualifies. Whether it beats cuFFT is
measured by ``benchmarks/fused_loop_speed.py`` on a GPU; it is not used by the models unless asked for.
"""

from __future__ import annotations

import functools
import math
import os

import torch

__all__ = ["available", "interpreting", "supports", "fused_slice_loop", "PRECISIONS", "split_factors", "digit_index"]


def split_factors(n: int) -> tuple[int, int]:
    """(n1, n2) with n1·n2 = n and n1 ≤ n2 as close to √n as possible (n1 = 1 for a prime)."""
    best = 1
    for a in range(1, int(math.isqrt(n)) + 1):
        if n % a == 0:
            best = a
    return best, n // best


def digit_index(n1: int, n2: int, device=None) -> torch.Tensor:
    """(n1, n2) natural frequency index ``k1 + n1·k2`` of each digit-order position [k1, k2] of a length n1·n2 axis."""
    return torch.arange(n1, device=device)[:, None] + n1 * torch.arange(n2, device=device)[None, :]

#: Triton ``input_precision`` of the small matrix products: "ieee" (float32 FMA) or "tf32x3" (tensor cores,
#: about float32 accuracy). "tf32" alone loses three decimal digits and is not offered.
PRECISIONS = ("ieee", "tf32x3")


@functools.lru_cache(maxsize=1)
def _triton_importable() -> bool:
    try:
        import triton  # noqa: F401
        import triton.language  # noqa: F401
    except Exception:
        return False
    return True


def interpreting(interpret: bool | None = None) -> bool:
    """``interpret``, or when None, whether the environment variable ``FDT_TRITON_INTERPRET`` is ``1`` (tests run
    the models' fused mode on the CPU that way; the interpreter is far too slow for real work)."""
    return os.environ.get("FDT_TRITON_INTERPRET") == "1" if interpret is None else bool(interpret)


def available(device: torch.device | str, *, interpret: bool | None = None) -> bool:
    """True when the fused loop can run on ``device``: Triton imports and the device is CUDA, or the CPU with
    ``interpret`` (Triton's interpreter; None: :func:`interpreting`).

    Triton is imported only when the device could use it: importing it in a process where napari has loaded
    Mesa's OpenGL (its libLLVM) crashes, so a CPU model without the interpreter must never touch it.
    """
    device = torch.device(device)
    if device.type == "cuda":
        could_run = torch.cuda.is_available()
    else:
        could_run = device.type == "cpu" and interpreting(interpret)
    return could_run and _triton_importable()


#: Largest factor of a grid side (its tile side in registers): sides up to 64·64 = 4096.
MAX_FACTOR = 64


def _tile(n: int, smallest: int) -> int:
    """Power of two ≥ max(n, smallest): the side of a register tile holding n points."""
    return max(smallest, 1 << max(0, int(n) - 1).bit_length())


def supports(shape: tuple[int, int], device: torch.device | str, *, interpret: bool | None = None) -> tuple[bool, str]:
    """(ok, reason): whether a (H, W) field grid qualifies for the fused kernels on ``device``."""
    interpret = interpreting(interpret)
    if not available(device, interpret=interpret):
        return False, "Triton is not importable, or the device is neither CUDA nor the CPU interpreter"
    for n in shape:
        n1, n2 = split_factors(int(n))
        if n2 > MAX_FACTOR:
            return False, f"grid side {n} splits into {n1}·{n2}; factors above {MAX_FACTOR} do not fit a register tile"
    return True, ""


@functools.lru_cache(maxsize=2)
def _kernels(interpret: bool):
    from napari_fdt.model import _triton_fused

    return _triton_fused.build(interpret)


class _Plan:
    """Grid factors, launch grids and the digit-order propagator for one (H, W) and kernel."""

    def __init__(self, shape: tuple[int, int], batch: int, interpret: bool, precision: str, min_tile: int | None) -> None:
        self.h, self.w = int(shape[0]), int(shape[1])
        self.n1h, self.n2h = split_factors(self.h)
        self.n1w, self.n2w = split_factors(self.w)
        smallest = min_tile or (1 if interpret else 16)
        self.p1h, self.p1w = _tile(self.n1h, smallest), _tile(self.n1w, smallest)
        self.p2h, self.p2w = _tile(self.n2h, smallest), _tile(self.n2w, smallest)
        # column digits per outer program: a tile of P1H·P1W·EB complex numbers (4096 at 512²)
        self.eb = max(1, min(_tile(self.n2w, 1), 4096 // (self.p1h * self.p1w)))
        self.outer_grid = (batch, self.n2h, -(-self.n2w // self.eb))
        self.inner_grid = (batch, self.n1h, self.n1w)
        self.interpret = interpret
        self.precision = precision
        self.outer, self.inner = _kernels(interpret)

    def consts(self) -> dict:
        return {"N1H": self.n1h, "N2H": self.n2h, "N1W": self.n1w, "N2W": self.n2w}

    def digit_kernel(self, kernel: torch.Tensor) -> torch.Tensor:
        """K/(H·W) in digit order, as interleaved float32 (H, W, 2), on the kernel's device (one gather per call)."""
        ih = digit_index(self.n1h, self.n2h, kernel.device)
        iw = digit_index(self.n1w, self.n2w, kernel.device)
        kd = kernel.detach().to(torch.complex64)[ih[:, :, None, None], iw[None, None, :, :]] / (self.h * self.w)
        return torch.view_as_real(kd.reshape(self.h, self.w).contiguous())

    def run_outer(self, x, phi_k, *, sign, inverse_in, forward_out, field=None, u=None, gphi=None) -> None:
        dummy = x
        self.outer[self.outer_grid](
            x, field if field is not None else dummy, u if u is not None else dummy, phi_k,
            gphi if gphi is not None else phi_k, self.h, self.w, **self.consts(), P1H=self.p1h, P1W=self.p1w,
            EB=self.eb, SIGN=sign,
            INVERSE_IN=inverse_in, PHI_GRAD=gphi is not None, STORE_FIELD=field is not None,
            FORWARD_OUT=forward_out, PRECISION=self.precision)

    def run_inner(self, x, kd, *, conj_k) -> None:
        self.inner[self.inner_grid](x, kd, self.h, self.w, **self.consts(), P2H=self.p2h, P2W=self.p2w,
                                    CONJ_K=conj_k, PRECISION=self.precision)


def _real(z: torch.Tensor) -> torch.Tensor:
    return torch.view_as_real(z)


class _FusedLoop(torch.autograd.Function):
    @staticmethod
    def forward(ctx, v0, phi, kernel, interpret: bool, precision: str, min_tile: int | None):  # type: ignore[override]
        b, n = v0.shape[0], phi.shape[0]
        plan = _Plan(tuple(v0.shape[-2:]), b, interpret, precision, min_tile)
        kd = plan.digit_kernel(kernel)
        phi_c = phi.detach().contiguous()
        work = v0.detach().clone(memory_format=torch.contiguous_format)
        fields = torch.empty((n, *v0.shape), dtype=torch.complex64, device=v0.device)
        w = _real(work)
        for k in range(n):
            last = k == n - 1
            plan.run_outer(w, phi_c[k], sign=1.0, inverse_in=k > 0, forward_out=not last, field=_real(fields[k]))
            if not last:
                plan.run_inner(w, kd, conj_k=False)
        ctx.plan = plan
        ctx.save_for_backward(phi_c, kd, fields)
        return fields[n - 1].clone()

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        phi, kd, fields = ctx.saved_tensors
        plan: _Plan = ctx.plan
        n = phi.shape[0]
        work = grad_out.detach().to(torch.complex64).clone(memory_format=torch.contiguous_format)
        w = _real(work)
        grad_phi = torch.zeros_like(phi)
        grad_v0 = torch.empty_like(work)
        for k in range(n - 1, -1, -1):
            first = k == 0
            plan.run_outer(w, phi[k], sign=-1.0, inverse_in=k < n - 1, forward_out=not first,
                           field=_real(grad_v0) if first else None, u=_real(fields[k]), gphi=grad_phi[k])
            if not first:
                plan.run_inner(w, kd, conj_k=True)
        return grad_v0, grad_phi, None, None, None, None


def fused_slice_loop(v0: torch.Tensor, phi: torch.Tensor, kernel: torch.Tensor, *, interpret: bool | None = None,
                     precision: str = "ieee", min_tile: int | None = None) -> torch.Tensor:
    """``u_{N−1}`` of the slice loop by the fused kernels; differentiable in ``v0`` and ``phi``.

    ``v0`` (B, H, W) complex64, ``phi`` (N, H, W) float32 screen phases (radians), ``kernel`` (H, W) the
    one-slice propagator in ``fft2`` order (no gradient). ``interpret`` runs CPU tensors through Triton's
    interpreter (None: :func:`interpreting`); ``precision`` one of :data:`PRECISIONS`; ``min_tile`` the smallest
    register-tile side (None: 16 on CUDA, 1 in the interpreter; tests set 16 to run the GPU's tiles in the
    interpreter). Raises ``ValueError`` when :func:`supports` says no.
    """
    interpret = interpreting(interpret) and v0.device.type == "cpu"
    ok, why = supports(tuple(v0.shape[-2:]), v0.device, interpret=interpret)
    if not ok:
        raise ValueError(f"fused slice loop: {why}")
    if precision not in PRECISIONS:
        raise ValueError(f"precision {precision!r}: one of {PRECISIONS}")
    if v0.dtype != torch.complex64 or phi.dtype != torch.float32:
        raise ValueError(f"fused slice loop needs complex64 fields and float32 phases, got {v0.dtype}, {phi.dtype}")
    if v0.ndim != 3 or phi.ndim != 3 or tuple(kernel.shape) != tuple(v0.shape[-2:]) or tuple(phi.shape[-2:]) != tuple(v0.shape[-2:]):
        raise ValueError(f"shapes do not match: v0 {tuple(v0.shape)}, phi {tuple(phi.shape)}, kernel {tuple(kernel.shape)}")
    if kernel.requires_grad:
        raise ValueError("the fused slice loop gives no gradient to the propagator; use slice_loop")
    return _FusedLoop.apply(v0, phi, kernel, interpret, precision, min_tile)
