"""The hand-written adjoint of the slice loop against plain autograd (the reference), every mode."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from napari_fdt import Optics
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.slice_loop import choose_mode, is_unitary, loop_bytes, slice_loop
from napari_fdt.physics.grid import frequency_grid, plan_for_sources
from napari_fdt.physics.propagation import propagation_kernel


def _reference(v0, phi, kernel):
    u = v0
    for k in range(phi.shape[0]):
        if k:
            u = torch.fft.ifft2(torch.fft.fft2(u) * kernel)
        u = u * torch.exp(1j * phi[k])
    return u


def _inputs(n_slices, shape=(12, 10), batch=3, unitary=True, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    cdt = torch.complex128 if dtype == torch.float64 else torch.complex64
    v0 = torch.randn((batch, *shape), generator=g, dtype=cdt)
    phi = 0.7 * torch.randn((n_slices, *shape), generator=g, dtype=dtype)
    fy, fx = frequency_grid(shape, 0.4, dtype=dtype)  # dx 0.4 µm: the whole grid propagates at n 1.33, λ 0.6
    f2 = fy * fy + fx * fx
    if not unitary:
        fy, fx = frequency_grid(shape, 0.15, dtype=dtype)  # finer than λ/(2n): evanescent corners, |K| < 1
        f2 = fy * fy + fx * fx
    kernel = propagation_kernel(f2, 1.5, 1.33, 0.6)
    if not unitary:  # a damped kernel as well, so no mode may rely on |K| = 1
        kernel = kernel * torch.exp(-0.1 * f2)
    return v0, phi, kernel


@pytest.mark.parametrize("mode", ["stored", "reversible", "checkpoint"])
@pytest.mark.parametrize("n_slices", [1, 2, 7])
def test_gradients_equal_autograd(mode, n_slices):
    unitary = mode == "reversible"
    v0, phi, kernel = _inputs(n_slices, unitary=unitary)
    w = torch.randn(v0.shape, dtype=v0.dtype, generator=torch.Generator().manual_seed(5))

    def loss(fn, a, b, c):
        u = fn(a, b, c)
        return (u.real * w.real + u.imag * w.imag).sum() + (u.abs() ** 2).sum() * 0.1

    grads = []
    for fn in (_reference, lambda a, b, c: slice_loop(a, b, c, mode)):
        a, b, c = (t.clone().requires_grad_() for t in (v0, phi, kernel))
        val = loss(fn, a, b, c)
        val.backward()
        grads.append((val.detach(), a.grad, b.grad, c.grad))
    (l_ref, *g_ref), (l_new, *g_new) = grads
    assert torch.allclose(l_ref, l_new, rtol=1e-12)
    for name, r, n in zip(("v0", "phi", "kernel"), g_ref, g_new):
        if r is None:  # one slice: the kernel is not used
            assert n is None or not n.abs().any()
            continue
        rel = float((n - r).abs().max() / r.abs().max())
        assert rel < 1e-10, f"{mode}: gradient of {name} differs by {rel:.2e}"


@pytest.mark.parametrize("mode", ["stored", "reversible", "checkpoint"])
def test_gradcheck(mode):
    v0, phi, kernel = _inputs(3, shape=(6, 5), batch=2, unitary=mode == "reversible")
    args = tuple(t.clone().requires_grad_() for t in (v0, phi, kernel))
    assert torch.autograd.gradcheck(lambda a, b, c: slice_loop(a, b, c, mode), args, eps=1e-6, atol=1e-6)


def test_reversible_float32_over_many_slices():
    """Re-propagating backwards through 96 slices in float32 loses little (the loop is unitary)."""
    v0, phi, kernel = _inputs(96, shape=(32, 32), batch=2, dtype=torch.float32)
    ref_in = tuple(t.to(torch.complex128 if t.is_complex() else torch.float64) for t in (v0, phi, kernel))
    grads = {}
    for name, args, mode in (("ref", ref_in, "stored"), ("rev", (v0, phi, kernel), "reversible")):
        a, b, c = (t.clone().requires_grad_() for t in args)
        (slice_loop(a, b, c, mode).abs() ** 2 * torch.linspace(0, 1, 32, dtype=b.dtype)).sum().backward()
        grads[name] = b.grad.double()
    rel = float((grads["rev"] - grads["ref"]).norm() / grads["ref"].norm())
    assert rel < 1e-4, rel


def test_unitarity_and_mode_choice():
    _, _, unit = _inputs(2, unitary=True)
    _, _, damped = _inputs(2, unitary=False)
    assert is_unitary(unit) and not is_unitary(damped)
    fb = 8 * 12 * 10
    stored = loop_bytes("stored", fb, 96, 30)
    assert loop_bytes("reversible", fb, 96, 30) < loop_bytes("checkpoint", fb, 96, 30) < stored
    # memory of the reversible mode does not grow with the number of slices
    assert loop_bytes("reversible", fb, 8, 30) == loop_bytes("reversible", fb, 960, 30)
    assert choose_mode(fb, 96, 30, True, None) == "stored"
    assert choose_mode(fb, 96, 30, True, stored) == "stored"
    assert choose_mode(fb, 96, 30, is_unitary(unit), stored - 1) == "reversible"
    assert choose_mode(fb, 96, 30, is_unitary(damped), stored - 1) == "checkpoint"


@pytest.mark.parametrize("mode", ["stored", "reversible", "checkpoint", "auto"])
def test_model_modes_agree_with_autograd(mode):
    """Through the whole model (sources, kernels with calibrated pixel size and spacing): same images, same gradients."""
    o = Optics(wavelength_um=0.6, na=0.6, n_background=1.33, pixel_size_um=0.35, n_slices=5,
               slice_spacing_um=1.0, image_plane_um=0.0)
    src = np.array([[0.5, -0.3, 12.0], [-1.0, 0.8, 14.0]])
    plan = plan_for_sources(o, (24, 20), src)
    dn = 0.02 * torch.rand((5, 24, 20), generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    out = {}
    for m in ("autograd", mode):
        model = MultiSliceModel(o, plan, device="cpu", dtype=torch.float64, backward_mode=m,
                                memory_budget_bytes=1 if mode == "auto" else None)
        d = dn.clone().requires_grad_()
        s = torch.tensor(src, dtype=torch.float64, requires_grad=True)
        px = torch.tensor(0.35, dtype=torch.float64, requires_grad=True)
        dz = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
        img = model(d, s, pixel_size_um=px, slice_spacing_um=dz)
        (img * torch.linspace(0.5, 1.5, 20, dtype=torch.float64)).sum().backward()
        out[m] = (img.detach(), d.grad, s.grad, px.grad, dz.grad)
    if mode == "auto":
        assert model.loop_mode(2) in ("reversible", "checkpoint")  # a 1-byte budget never allows "stored"
    for name, r, n in zip(("images", "delta_n", "sources", "pixel", "spacing"), out["autograd"], out[mode]):
        rel = float((n - r).abs().max() / r.abs().max())
        assert rel < 1e-9, f"{mode}: {name} differs by {rel:.2e}"


def test_no_grad_inference_matches():
    o = Optics(wavelength_um=0.6, na=0.6, n_background=1.33, pixel_size_um=0.35, n_slices=4,
               slice_spacing_um=1.0, image_plane_um=0.0)
    src = np.array([[0.5, -0.3, 12.0]])
    plan = plan_for_sources(o, (16, 16), src)
    dn = 0.03 * torch.rand((4, 16, 16), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    a = MultiSliceModel(o, plan, device="cpu", dtype=torch.float64, backward_mode="autograd")(dn, torch.tensor(src))
    with torch.no_grad():
        b = MultiSliceModel(o, plan, device="cpu", dtype=torch.float64)(dn, torch.tensor(src))
    assert float((a - b).abs().max() / a.abs().max()) < 1e-12
    assert math.isfinite(float(b.sum()))
