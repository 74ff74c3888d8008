"""The DFT-matrix form of the slice loop against torch.fft and the package's slice loop (float64 reference)."""

from __future__ import annotations

import pytest
import torch

from benchmarks._dft_loop import DftPlan, dft_slice_loop
from napari_fdt.model.fused_loop import split_factors
from napari_fdt.model.slice_loop import slice_loop
from napari_fdt.physics.propagation import propagation_kernel


@pytest.mark.parametrize("shape", [(12, 10), (16, 15), (7, 9)])
def test_transforms_are_the_dft(shape) -> None:
    """fft2 in digit order = torch.fft.fft2 permuted; ifft2 = the unnormalised inverse (ifft2 with norm="forward")."""
    gen = torch.Generator().manual_seed(0)
    u = torch.randn(3, *shape, generator=gen, dtype=torch.complex128)
    plan = DftPlan(shape, dtype=torch.complex128)
    spec = plan.fft2(u)
    ref = torch.fft.fft2(u)
    for b in range(3):
        assert torch.allclose(spec[b], plan.permute(ref[b]), atol=1e-11)
    assert torch.allclose(plan.ifft2(spec), torch.fft.ifft2(ref, norm="forward"), atol=1e-10)


def test_split_factors() -> None:
    assert split_factors(512) == (16, 32) and split_factors(600) == (24, 25) and split_factors(13) == (1, 13)


def _loop_inputs(dtype):
    gen = torch.Generator().manual_seed(1)
    h, w, n = 20, 18, 4
    fy = torch.fft.fftfreq(h, 0.33, dtype=torch.float64)[:, None]
    fx = torch.fft.fftfreq(w, 0.33, dtype=torch.float64)[None, :]
    kernel = propagation_kernel(fy**2 + fx**2, 1.5, 1.33, 0.6)
    v0 = torch.randn(2, h, w, generator=gen, dtype=torch.complex128)
    phi = 0.5 * torch.rand(n, h, w, generator=gen, dtype=torch.float64)
    weight = torch.rand(2, h, w, generator=gen, dtype=torch.float64)
    cplx = torch.complex64 if dtype == torch.float32 else torch.complex128
    return v0.to(cplx).requires_grad_(), phi.to(dtype).requires_grad_(), kernel.to(cplx).requires_grad_(), weight.to(dtype)


def _loss(loop, v0, phi, kernel, weight):
    u = loop(v0, phi, kernel)
    return ((u.real.square() + u.imag.square()) * weight).sum()


def test_loop_and_gradients_match_the_fft_loop_in_float64() -> None:
    v0, phi, kernel, weight = _loop_inputs(torch.float64)
    a = _loss(dft_slice_loop, v0, phi, kernel, weight)
    b = _loss(lambda *x: slice_loop(*x, mode="stored"), v0, phi, kernel, weight)
    assert float(abs(a - b) / abs(b)) < 1e-12
    ga = torch.autograd.grad(a, (v0, phi, kernel))
    gb = torch.autograd.grad(b, (v0, phi, kernel))
    for x, y in zip(ga, gb):
        assert float((x - y).norm() / y.norm()) < 1e-10


def test_float32_gradients_within_1e_5_of_the_float64_reference() -> None:
    """The issue's accuracy target for a custom slice kernel: gradients within 1e-5 (relative) of float64."""
    v0, phi, kernel, weight = _loop_inputs(torch.float64)
    ref = torch.autograd.grad(_loss(lambda *x: slice_loop(*x, mode="stored"), v0, phi, kernel, weight), (v0, phi, kernel))
    v32, p32, k32, w32 = _loop_inputs(torch.float32)
    got = torch.autograd.grad(_loss(dft_slice_loop, v32, p32, k32, w32), (v32, p32, k32))
    for x, y in zip(got, ref):
        assert float((x.to(y.dtype) - y).norm() / y.norm()) < 1e-5
