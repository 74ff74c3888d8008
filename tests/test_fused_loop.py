"""The fused Triton slice loop (issue 16, item 2) against the float64 FFT loop, run by Triton's CPU interpreter.

The kernels are the ones a GPU compiles; the interpreter executes them with numpy, so their index arithmetic,
masks, in-place passes and adjoint are checked here without a GPU (their speed is not: ``benchmarks/``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from napari_fdt.errors import FDTInputError
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.fused_loop import _triton_importable, fused_slice_loop, supports
from napari_fdt.model.slice_loop import _adjoint_screen, slice_loop
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.optics import Optics
from napari_fdt.physics.propagation import propagation_kernel
from napari_fdt.recon.config import SolverConfig, StageConfig
from napari_fdt.recon.solver import Reconstructor
from napari_fdt.sim.simulate import simulate, source_grid

needs_triton = pytest.mark.skipif(not _triton_importable(), reason="Triton is not installed (the test extra installs it on Linux x86-64)")


def _case(shape, n_slices, batch, seed=0):
    """float64 inputs of the loop: field v0, phases φ (radians), the one-slice propagator, a loss weight."""
    gen = torch.Generator().manual_seed(seed)
    h, w = shape
    fy = torch.fft.fftfreq(h, 0.33, dtype=torch.float64)[:, None]
    fx = torch.fft.fftfreq(w, 0.33, dtype=torch.float64)[None, :]
    kernel = propagation_kernel(fy**2 + fx**2, 1.5, 1.33, 0.6)
    v0 = torch.randn(batch, h, w, generator=gen, dtype=torch.complex128)
    phi = 0.5 * torch.rand(n_slices, h, w, generator=gen, dtype=torch.float64)
    weight = torch.rand(batch, h, w, generator=gen, dtype=torch.float64)
    return v0, phi, kernel, weight


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.to(b.dtype) - b).norm() / b.norm())


@pytest.mark.parametrize("shape, n_slices, batch, min_tile", [
    ((32, 32), 3, 2, None),   # powers of two: tiles without padding
    ((24, 40), 3, 2, None),   # 2·3·5-smooth sides as plan_grid makes them: masked tiles
    ((13, 16), 2, 1, None),   # a prime side: one factor is 1
    ((48, 40), 2, 1, 16),     # the tiles a GPU uses (≥ 16, tl.dot's smallest), mostly padding here
    ((20, 20), 1, 2, None),   # one slice: the screen alone
])
@needs_triton
def test_loop_and_gradients_within_1e_5_of_float64(shape, n_slices, batch, min_tile) -> None:
    """Field and gradients (v0, φ) of a weighted |u|² loss: the issue's target is 1e-5 of the float64 reference."""
    v0, phi, kernel, weight = _case(shape, n_slices, batch)
    ref_v0, ref_phi = v0.clone().requires_grad_(), phi.clone().requires_grad_()
    ref = slice_loop(ref_v0, ref_phi, kernel, mode="stored")
    ref_grads = torch.autograd.grad((ref.abs().square() * weight).sum(), (ref_v0, ref_phi))
    f_v0, f_phi = v0.to(torch.complex64).requires_grad_(), phi.float().requires_grad_()
    u = fused_slice_loop(f_v0, f_phi, kernel.to(torch.complex64), interpret=True, min_tile=min_tile)
    grads = torch.autograd.grad((u.abs().square() * weight.float()).sum(), (f_v0, f_phi))
    assert _rel(u.detach(), ref.detach()) < 1e-5
    assert _rel(grads[0], ref_grads[0]) < 1e-5
    if n_slices > 1:  # with one slice |u|² does not depend on φ: its gradient is zero
        assert _rel(grads[1], ref_grads[1]) < 1e-5
    else:
        assert float(grads[1].abs().max()) < 1e-5 * float(weight.sum())


@needs_triton
def test_propagation_alone_is_the_fft_propagation() -> None:
    """Zero phases: the loop is (N−1) free propagations, ifft2(K^(N−1)·fft2(v0)), an independent closed form."""
    v0, phi, kernel, _ = _case((24, 40), 4, 2, seed=3)
    expected = torch.fft.ifft2(kernel**3 * torch.fft.fft2(v0))
    u = fused_slice_loop(v0.to(torch.complex64), torch.zeros_like(phi, dtype=torch.float32),
                         kernel.to(torch.complex64), interpret=True)
    assert _rel(u, expected) < 1e-6


@needs_triton
def test_adjoint_screen_kernel_matches_torch() -> None:
    """The older fused kernel (one screen's adjoint, used by slice_loop on CUDA), interpreted, equals its torch form."""
    from napari_fdt.model._triton_slice import adjoint_screen

    gen = torch.Generator().manual_seed(4)
    g = torch.randn(3, 20, 24, generator=gen, dtype=torch.complex64)
    u = torch.randn(3, 20, 24, generator=gen, dtype=torch.complex64)
    phi = torch.rand(20, 24, generator=gen)
    g_ref, v_ref = g.clone(), torch.empty_like(u)
    gp_ref = _adjoint_screen(g_ref, u, phi, v_ref)
    g_tri, v_tri = g.clone(), torch.empty_like(u)
    gp_tri = adjoint_screen(g_tri, u, phi, v_tri, interpret=True)
    assert _rel(gp_tri, gp_ref) < 1e-6 and _rel(g_tri, g_ref) < 1e-6 and _rel(v_tri, v_ref) < 1e-6


OPTICS = Optics(wavelength_um=0.6, na=0.6, n_background=1.33, pixel_size_um=0.35, n_slices=4,
                slice_spacing_um=1.0, image_plane_um=0.0)
SOURCES = np.array([[0.5, -0.3, 10.0], [-1.0, 0.8, 11.0]])


@needs_triton
def test_model_fused_mode_equals_stored(monkeypatch) -> None:
    """``backward_mode="fused"`` in the whole model (interpreter): images and gradients of Δn and sources as "stored"."""
    monkeypatch.setenv("FDT_TRITON_INTERPRET", "1")
    plan = plan_for_sources(OPTICS, (16, 16), SOURCES)
    dn = 0.02 * torch.rand((4, 16, 16), generator=torch.Generator().manual_seed(2))
    out = {}
    for mode in ("stored", "fused"):
        model = MultiSliceModel(OPTICS, plan, device="cpu", backward_mode=mode)
        d = dn.clone().requires_grad_()
        s = torch.tensor(SOURCES, dtype=torch.float32, requires_grad=True)
        img = model(d, s)
        (img * torch.linspace(0.5, 1.5, 16)).sum().backward()
        out[mode] = (img.detach(), d.grad, s.grad)
    for name, a, b in zip(("images", "delta_n", "sources"), out["stored"], out["fused"]):
        assert _rel(b, a) < 1e-5, name


def test_fused_mode_refused_on_cpu_without_interpreter(monkeypatch) -> None:
    """On the CPU the fused mode is a user error (named field and fix), raised when the model is built."""
    monkeypatch.delenv("FDT_TRITON_INTERPRET", raising=False)
    plan = plan_for_sources(OPTICS, (16, 16), SOURCES)
    assert not supports(plan.padded_shape, "cpu")[0]
    with pytest.raises(FDTInputError, match="backward_mode"):
        MultiSliceModel(OPTICS, plan, device="cpu", backward_mode="fused")


def test_fused_mode_refused_before_the_run(monkeypatch) -> None:
    """A reconstruction asking for the fused mode on the CPU is refused in the constructor, before any stage runs."""
    monkeypatch.delenv("FDT_TRITON_INTERPRET", raising=False)
    sim = simulate(np.zeros((4, 32, 32), np.float32), OPTICS, source_grid(3, 6.0, 12.0), noise=False, device="cpu")
    with pytest.raises(FDTInputError, match="backward_mode.*'fused' cannot run on cpu"):
        Reconstructor(sim.acquisition, SolverConfig(stages=[StageConfig(1, 2)], backward_mode="fused"), device="cpu")


def test_cpu_model_does_not_import_triton() -> None:
    """A CPU model without the interpreter never imports Triton (importing it where napari has loaded Mesa's
    OpenGL, libLLVM, crashes the process): a fresh interpreter builds a model, renders an image, takes a gradient
    and asks for the fused mode, and Triton is still not in ``sys.modules``."""
    code = textwrap.dedent("""
        import sys
        import numpy as np
        import torch
        from napari_fdt.errors import FDTInputError
        from napari_fdt.model.forward import MultiSliceModel
        from napari_fdt.model.fused_loop import available, supports
        from napari_fdt.model.render import render_images
        from napari_fdt.physics.grid import plan_for_sources
        from napari_fdt.physics.optics import Optics

        optics = Optics(wavelength_um=0.6, na=0.6, n_background=1.33, pixel_size_um=0.35, n_slices=4,
                        slice_spacing_um=1.0, image_plane_um=0.0)
        src = np.array([[0.5, -0.3, 10.0]])
        model = MultiSliceModel(optics, plan_for_sources(optics, (16, 16), src), device="cpu")
        image = render_images(model, np.zeros((4, 16, 16), np.float32), src)
        assert image.shape == (1, 16, 16) and float(image.sum()) > 0
        dn = torch.zeros((4, 16, 16), requires_grad=True)
        model(dn, torch.tensor(src, dtype=torch.float32)).sum().backward()
        assert not available("cpu") and not supports(model.plan.padded_shape, "cpu")[0]
        try:
            MultiSliceModel(optics, model.plan, device="cpu", backward_mode="fused")
        except FDTInputError:
            pass
        print("triton" in sys.modules)
    """)
    env = {k: v for k, v in os.environ.items() if k != "FDT_TRITON_INTERPRET"}
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip().splitlines()[-1] == "False", run.stdout
