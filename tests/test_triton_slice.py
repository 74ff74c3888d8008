"""The slice loop's Triton kernel (one screen's adjoint, :mod:`napari_fdt.model._triton_slice`), run by Triton's CPU
interpreter, and the rule that a CPU-only model never imports Triton.

The kernel is the one a GPU compiles; the interpreter executes it with numpy, so its index arithmetic, masks and
in-place writes are checked here without a GPU (its compiled form: ``benchmarks/gpu_checks.py``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
import torch

from napari_fdt.model._triton_slice import adjoint_screen, triton_importable
from napari_fdt.model.slice_loop import _adjoint_screen

# (asked at collection, before any napari test has loaded an OpenGL driver that Triton's import would meet)
needs_triton = pytest.mark.skipif(not triton_importable(), reason="Triton is not installed (the test extra installs it on Linux x86-64)")


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.to(b.dtype) - b).norm() / b.norm())


@needs_triton
@pytest.mark.parametrize("write_v", [True, False])
def test_adjoint_screen_kernel_matches_torch(write_v: bool) -> None:
    """The kernel, interpreted, equals the torch form of one screen's adjoint (with and without ``u·conj(P)``)."""
    gen = torch.Generator().manual_seed(4)
    g = torch.randn(3, 20, 24, generator=gen, dtype=torch.complex64)
    u = torch.randn(3, 20, 24, generator=gen, dtype=torch.complex64)
    phi = torch.rand(20, 24, generator=gen)
    g_ref, v_ref = g.clone(), (torch.empty_like(u) if write_v else None)
    gp_ref = _adjoint_screen(g_ref, u, phi, v_ref)
    g_tri, v_tri = g.clone(), (torch.empty_like(u) if write_v else None)
    gp_tri = adjoint_screen(g_tri, u, phi, v_tri, interpret=True)
    assert _rel(gp_tri, gp_ref) < 1e-6 and _rel(g_tri, g_ref) < 1e-6
    if write_v:
        assert _rel(v_tri, v_ref) < 1e-6
    # written into a row of a caller's gradient (the slice loop's backward passes grad_phi[k]), the same numbers
    rows = torch.full((2, 20, 24), 7.0)
    g_out = g.clone()
    assert adjoint_screen(g_out, u, phi, None, out=rows[1], interpret=True).data_ptr() == rows[1].data_ptr()
    assert _rel(rows[1], gp_ref) < 1e-6 and bool((rows[0] == 7.0).all())
    torch_rows = torch.full((2, 20, 24), 7.0)
    _adjoint_screen(g.clone(), u, phi, None, torch_rows[1])
    assert torch.equal(torch_rows[1], gp_ref) and bool((torch_rows[0] == 7.0).all())


def test_cpu_model_does_not_import_triton() -> None:
    """A CPU model never imports Triton (importing it where napari has loaded Mesa's OpenGL, libLLVM, crashes the
    process): a fresh interpreter builds a model, renders an image, takes a gradient through the slice loop and asks
    whether the kernel is available, and Triton is still not in ``sys.modules``."""
    code = textwrap.dedent("""
        import sys
        import numpy as np
        import torch
        from napari_fdt.model import _triton_slice
        from napari_fdt.model.forward import MultiSliceModel
        from napari_fdt.model.render import render_images
        from napari_fdt.physics.grid import plan_for_sources
        from napari_fdt.physics.optics import Optics

        optics = Optics(wavelength_um=0.6, na=0.6, n_background=1.33, pixel_size_um=0.35, n_slices=4,
                        slice_spacing_um=1.0, image_plane_um=0.0)
        src = np.array([[0.5, -0.3, 10.0]])
        model = MultiSliceModel(optics, plan_for_sources(optics, (16, 16), src), device="cpu", backward_mode="stored")
        image = render_images(model, np.zeros((4, 16, 16), np.float32), src)
        assert image.shape == (1, 16, 16) and float(image.sum()) > 0
        dn = torch.zeros((4, 16, 16), requires_grad=True)
        model(dn, torch.tensor(src, dtype=torch.float32)).sum().backward()
        assert dn.grad is not None and not _triton_slice.available()
        print("triton" in sys.modules)
    """)
    env = dict(os.environ, CUDA_VISIBLE_DEVICES="")  # a CPU-only process even on a machine with a GPU
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip().splitlines()[-1] == "False", run.stdout
