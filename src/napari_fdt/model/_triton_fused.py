"""Triton kernels of the fused slice loop (:mod:`napari_fdt.model.fused_loop`); imported only when Triton is.

Both kernels work on (B, H, W) complex64 fields stored as interleaved float32 (``torch.view_as_real``), with
H = N1H·N2H and W = N1W·N2W (any factors; each tile side is padded to a power of two P ≥ N, masked, with the
small DFT matrices zero on the padding). A pixel (row, column) = (N2H·a + c, N2W·d + e) has the flat offset
``(N2H·a + c)·W + N2W·d + e``; every intermediate of the four-step transform (``benchmarks/_dft_loop.py``)
is stored at the offset of its digits in the same formula, so no kernel ever transposes memory.

``outer_kernel`` — one program per (image b, high-row-digit c, block of EB column digits e); its tile runs over
the first digits (a, d) = (p, q):
    [INVERSE_IN] conj(F1h) ⊗ conj(F1w) over (p, q), the last half of an unnormalised inverse DFT;
    [PHI_GRAD]   ∇φ += Im(x·conj(u)) with u a stored field (atomic add over images);
    screen       x ← x·exp(i·SIGN·φ);
    [STORE_FIELD] x written to ``field``;
    [FORWARD_OUT] F1h ⊗ F1w over (a, d) and the twiddle W_H^{p·c}·W_W^{q·e}, the first half of a DFT, written
    back in place.

``inner_kernel`` — one program per (b, p, q); its tile (c, e) is an N2H × N2W matrix A:
    S = F2h·A·F2w (second half of the DFT), S ← S·K (or conj(K); K stored in digit order, already divided by
    H·W), C = conj(F2h)·S·conj(F2w) (first half of the inverse), C ← C·conj(twiddle), written back in place.

Each kernel is self-contained (the masked tile load and the small DFT matrices are written out in both): a helper
decorated with ``triton.jit`` cannot be called from a kernel that Triton's interpreter runs through
``InterpretedFunction`` (the same reason ``tl.zeros``, a jit function, is avoided below).

The small DFT matrices and twiddles are computed in registers from integer phases (exact modulo N). Complex
products are four real ``tl.dot`` calls; ``PRECISION`` is Triton's ``input_precision`` ("ieee" for float32
products; "tf32x3" uses tensor cores at about float32 accuracy).
"""

from __future__ import annotations

import math

import triton
import triton.language as tl

TWO_PI = tl.constexpr(2.0 * math.pi)  # a global a kernel reads must be a constexpr (Triton 3.6 refuses a plain float)


def _outer(x_ptr, field_ptr, u_ptr, phi_ptr, gphi_ptr, H, W,
           N1H: tl.constexpr, N2H: tl.constexpr, N1W: tl.constexpr, N2W: tl.constexpr,
           P1H: tl.constexpr, P1W: tl.constexpr, EB: tl.constexpr,
           SIGN: tl.constexpr, INVERSE_IN: tl.constexpr, PHI_GRAD: tl.constexpr, STORE_FIELD: tl.constexpr,
           FORWARD_OUT: tl.constexpr, PRECISION: tl.constexpr):
    b = tl.program_id(0)
    c = tl.program_id(1)
    e0 = tl.program_id(2) * EB
    ia = tl.arange(0, P1H)
    id_ = tl.arange(0, P1W)
    ie = tl.arange(0, EB)
    ma = ia < N1H
    md = id_ < N1W
    mask = ma[:, None, None] & md[None, :, None] & ((e0 + ie) < N2W)[None, None, :]
    pix = ((N2H * ia[:, None, None] + c) * W + N2W * id_[None, :, None] + e0 + ie[None, None, :])
    pix = tl.where(mask, pix, 0)
    base = (b.to(tl.int64) * H * W + pix) * 2  # int64 first: B·H·W·2 may pass 2**31
    xr = tl.load(x_ptr + base, mask=mask, other=0.0)
    xi = tl.load(x_ptr + base + 1, mask=mask, other=0.0)
    # small DFT matrices F[j, k] = exp(−2πi·jk/N) (symmetric; the inverse uses conj(F)), zero on the tile's padding
    mh = ma[:, None] & ma[None, :]
    ang_h = (TWO_PI / N1H) * ((ia[:, None] * ia[None, :]) % N1H).to(tl.float32)
    fhr = tl.where(mh, tl.cos(ang_h), 0.0)
    fhi = tl.where(mh, -tl.sin(ang_h), 0.0)
    mw = md[:, None] & md[None, :]
    ang_w = (TWO_PI / N1W) * ((id_[:, None] * id_[None, :]) % N1W).to(tl.float32)
    fwr = tl.where(mw, tl.cos(ang_w), 0.0)
    fwi = tl.where(mw, -tl.sin(ang_w), 0.0)
    if INVERSE_IN:
        # over the first axis (p → a): X ← conj(Fh)·X, X as (N1H, N1W·EB)
        yr = tl.reshape(xr, (P1H, P1W * EB))
        yi = tl.reshape(xi, (P1H, P1W * EB))
        zr = tl.dot(fhr, yr, input_precision=PRECISION) + tl.dot(fhi, yi, input_precision=PRECISION)
        zi = tl.dot(fhr, yi, input_precision=PRECISION) - tl.dot(fhi, yr, input_precision=PRECISION)
        # over the second axis (q → d): permute to (N1W, N1H·EB)
        yr = tl.reshape(tl.permute(tl.reshape(zr, (P1H, P1W, EB)), (1, 0, 2)), (P1W, P1H * EB))
        yi = tl.reshape(tl.permute(tl.reshape(zi, (P1H, P1W, EB)), (1, 0, 2)), (P1W, P1H * EB))
        zr = tl.dot(fwr, yr, input_precision=PRECISION) + tl.dot(fwi, yi, input_precision=PRECISION)
        zi = tl.dot(fwr, yi, input_precision=PRECISION) - tl.dot(fwi, yr, input_precision=PRECISION)
        xr = tl.permute(tl.reshape(zr, (P1W, P1H, EB)), (1, 0, 2))
        xi = tl.permute(tl.reshape(zi, (P1W, P1H, EB)), (1, 0, 2))
    phi = tl.load(phi_ptr + pix, mask=mask, other=0.0)
    if PHI_GRAD:
        ur = tl.load(u_ptr + base, mask=mask, other=0.0)
        ui = tl.load(u_ptr + base + 1, mask=mask, other=0.0)
        tl.atomic_add(gphi_ptr + pix, xi * ur - xr * ui, mask=mask)
    cs = tl.cos(phi)
    sn = SIGN * tl.sin(phi)
    tr = xr * cs - xi * sn
    xi = xr * sn + xi * cs
    xr = tr
    if STORE_FIELD:
        tl.store(field_ptr + base, xr, mask=mask)
        tl.store(field_ptr + base + 1, xi, mask=mask)
    if FORWARD_OUT:
        yr = tl.reshape(xr, (P1H, P1W * EB))
        yi = tl.reshape(xi, (P1H, P1W * EB))
        zr = tl.dot(fhr, yr, input_precision=PRECISION) - tl.dot(fhi, yi, input_precision=PRECISION)
        zi = tl.dot(fhr, yi, input_precision=PRECISION) + tl.dot(fhi, yr, input_precision=PRECISION)
        yr = tl.reshape(tl.permute(tl.reshape(zr, (P1H, P1W, EB)), (1, 0, 2)), (P1W, P1H * EB))
        yi = tl.reshape(tl.permute(tl.reshape(zi, (P1H, P1W, EB)), (1, 0, 2)), (P1W, P1H * EB))
        zr = tl.dot(fwr, yr, input_precision=PRECISION) - tl.dot(fwi, yi, input_precision=PRECISION)
        zi = tl.dot(fwr, yi, input_precision=PRECISION) + tl.dot(fwi, yr, input_precision=PRECISION)
        xr = tl.permute(tl.reshape(zr, (P1W, P1H, EB)), (1, 0, 2))
        xi = tl.permute(tl.reshape(zi, (P1W, P1H, EB)), (1, 0, 2))
        # twiddle W_H^{p·c}·W_W^{q·e} (p, q now the first digits of the spectrum)
        tw = -TWO_PI * (((ia[:, None, None] * c) % H).to(tl.float32) / H
                        + ((id_[None, :, None] * (e0 + ie[None, None, :])) % W).to(tl.float32) / W)
        cs = tl.cos(tw)
        sn = tl.sin(tw)
        tr = xr * cs - xi * sn
        xi = xr * sn + xi * cs
        xr = tr
        tl.store(x_ptr + base, xr, mask=mask)
        tl.store(x_ptr + base + 1, xi, mask=mask)


def _inner(x_ptr, k_ptr, H, W,
           N1H: tl.constexpr, N2H: tl.constexpr, N1W: tl.constexpr, N2W: tl.constexpr,
           P2H: tl.constexpr, P2W: tl.constexpr, CONJ_K: tl.constexpr, PRECISION: tl.constexpr):
    b = tl.program_id(0)
    p = tl.program_id(1)
    q = tl.program_id(2)
    ic = tl.arange(0, P2H)
    ie = tl.arange(0, P2W)
    mc = ic < N2H
    me = ie < N2W
    mask = mc[:, None] & me[None, :]
    pix = tl.where(mask, (N2H * p + ic[:, None]) * W + N2W * q + ie[None, :], 0)
    base = (b.to(tl.int64) * H * W + pix) * 2  # int64 first: B·H·W·2 may pass 2**31
    ar = tl.load(x_ptr + base, mask=mask, other=0.0)
    ai = tl.load(x_ptr + base + 1, mask=mask, other=0.0)
    mh = mc[:, None] & mc[None, :]
    ang_h = (TWO_PI / N2H) * ((ic[:, None] * ic[None, :]) % N2H).to(tl.float32)
    fhr = tl.where(mh, tl.cos(ang_h), 0.0)
    fhi = tl.where(mh, -tl.sin(ang_h), 0.0)
    mw = me[:, None] & me[None, :]
    ang_w = (TWO_PI / N2W) * ((ie[:, None] * ie[None, :]) % N2W).to(tl.float32)
    fwr = tl.where(mw, tl.cos(ang_w), 0.0)
    fwi = tl.where(mw, -tl.sin(ang_w), 0.0)
    # S = Fh·A·Fw
    tr = tl.dot(fhr, ar, input_precision=PRECISION) - tl.dot(fhi, ai, input_precision=PRECISION)
    ti = tl.dot(fhr, ai, input_precision=PRECISION) + tl.dot(fhi, ar, input_precision=PRECISION)
    sr = tl.dot(tr, fwr, input_precision=PRECISION) - tl.dot(ti, fwi, input_precision=PRECISION)
    si = tl.dot(tr, fwi, input_precision=PRECISION) + tl.dot(ti, fwr, input_precision=PRECISION)
    kr = tl.load(k_ptr + pix * 2, mask=mask, other=0.0)
    ki = tl.load(k_ptr + pix * 2 + 1, mask=mask, other=0.0)
    if CONJ_K:
        ki = -ki
    tr = sr * kr - si * ki
    si = sr * ki + si * kr
    sr = tr
    # C = conj(Fh)·S·conj(Fw)
    tr = tl.dot(fhr, sr, input_precision=PRECISION) + tl.dot(fhi, si, input_precision=PRECISION)
    ti = tl.dot(fhr, si, input_precision=PRECISION) - tl.dot(fhi, sr, input_precision=PRECISION)
    cr = tl.dot(tr, fwr, input_precision=PRECISION) + tl.dot(ti, fwi, input_precision=PRECISION)
    ci = tl.dot(ti, fwr, input_precision=PRECISION) - tl.dot(tr, fwi, input_precision=PRECISION)
    # conj twiddle: exp(+2πi·(p·n/H + q·m/W)), (n, m) the second digits of the inverse's output
    tw = TWO_PI * (((p * ic[:, None]) % H).to(tl.float32) / H + ((q * ie[None, :]) % W).to(tl.float32) / W)
    cs = tl.cos(tw)
    sn = tl.sin(tw)
    tl.store(x_ptr + base, cr * cs - ci * sn, mask=mask)
    tl.store(x_ptr + base + 1, cr * sn + ci * cs, mask=mask)


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


def build(interpret: bool):
    """(outer, inner) kernels: compiled for CUDA, or run by Triton's CPU interpreter when ``interpret``."""
    if interpret:
        from triton.runtime.interpreter import InterpretedFunction

        return InterpretedFunction(_outer), InterpretedFunction(_inner)
    return triton.jit(_outer), triton.jit(_inner)
