"""Gradients of the forward model against finite differences, and precision/device agreement."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.optics import Optics


def _tiny_model(dtype=torch.float64, device="cpu") -> tuple[MultiSliceModel, np.ndarray]:
    opt = Optics(wavelength_um=0.6, n_background=1.33, na=0.6, pixel_size_um=0.4, n_slices=3,
                 slice_spacing_um=1.0, image_plane_um=0.7)
    src = np.array([[0.3, -0.2, 4.0], [-0.5, 0.6, 5.0]])
    return MultiSliceModel(opt, plan_for_sources(opt, (10, 12), src), device=device, dtype=dtype), src


def test_gradients_match_finite_differences() -> None:
    model, src = _tiny_model()
    gen = torch.Generator().manual_seed(0)
    dn = (0.01 * torch.rand(3, 10, 12, generator=gen, dtype=torch.float64)).requires_grad_()
    sources = torch.tensor(src, requires_grad=True)
    gain = torch.tensor([1.0, 0.7], dtype=torch.float64, requires_grad=True)
    weights = torch.rand(2, 10, 12, generator=gen, dtype=torch.float64)

    def loss(dn, sources, gain):
        return (model(dn, sources, gain) * weights).sum()

    assert torch.autograd.gradcheck(loss, (dn, sources, gain), eps=1e-6, atol=1e-7, rtol=1e-5)


def _scene(model: MultiSliceModel, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = model.optics.n_slices
    h, w = model.plan.image_shape
    dn = np.zeros((n, h, w))
    yy, xx = np.mgrid[:h, :w]
    for _ in range(6):
        k, cy, cx = rng.integers(n), rng.uniform(0, h), rng.uniform(0, w)
        dn[k] += 0.03 * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * 4.0**2))
    src = np.column_stack([rng.uniform(-8, 8, 4), rng.uniform(-8, 8, 4), rng.uniform(40, 60, 4)])
    return dn, src


def test_float32_agrees_with_float64() -> None:
    opt = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.3, n_slices=8,
                 slice_spacing_um=2.0, image_plane_um=3.0)
    ref_src = np.array([[8.0, 8.0, 60.0]])
    m64 = MultiSliceModel(opt, plan_for_sources(opt, (96, 96), ref_src), device="cpu", dtype=torch.float64)
    m32 = MultiSliceModel(opt, m64.plan, device="cpu", dtype=torch.float32)
    dn, src = _scene(m64)
    i64 = m64(torch.tensor(dn), torch.tensor(src)).numpy()
    i32 = m32(torch.tensor(dn, dtype=torch.float32), torch.tensor(src, dtype=torch.float32)).numpy()
    rel = np.linalg.norm(i32 - i64) / np.linalg.norm(i64)
    assert rel < 2e-5, rel


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("mode", ["stored", "reversible", "checkpoint", "autograd"])
def test_cpu_agrees_with_cuda(mode) -> None:
    """float32 on CPU and on CUDA both within float32 rounding of a float64 CPU reference (images and gradients)."""
    # 0.3 µm pixels put evanescent corners on the grid; the reversible mode needs a grid without (0.35 µm)
    pixel = 0.35 if mode == "reversible" else 0.3
    opt = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=pixel, n_slices=8,
                 slice_spacing_um=2.0, image_plane_um=3.0)
    plan = plan_for_sources(opt, (96, 96), np.array([[8.0, 8.0, 60.0]]))
    ref = MultiSliceModel(opt, plan, device="cpu", dtype=torch.float64, backward_mode="autograd")
    dn, src = _scene(ref)
    out = {}
    for name, m, dt in (("ref", ref, torch.float64),
                        ("cpu", MultiSliceModel(opt, plan, device="cpu", backward_mode=mode), torch.float32),
                        ("cuda", MultiSliceModel(opt, plan, device="cuda", backward_mode=mode), torch.float32)):
        x = torch.tensor(dn, dtype=dt, device=m.device).requires_grad_()
        img = m(x, torch.tensor(src, dtype=dt))
        (img * torch.linspace(0.5, 1.5, img.shape[-1], dtype=dt, device=m.device)).sum().backward()
        out[name] = (img.detach().cpu().double().numpy(), x.grad.cpu().double().numpy())
    for name in ("cpu", "cuda"):
        for what, a, r, bound in (("images", out[name][0], out["ref"][0], 2e-5), ("gradient", out[name][1], out["ref"][1], 1e-4)):
            rel = np.linalg.norm(a - r) / np.linalg.norm(r)
            assert rel < bound, f"{name} {mode} {what}: {rel:.2e}"


def test_gradients_of_optical_parameters_match_finite_differences() -> None:
    """Pixel size, slice spacing and wavelength, passed as tensors, are differentiable (self-calibration)."""
    model, src = _tiny_model()
    gen = torch.Generator().manual_seed(2)
    dn = 0.01 * torch.rand(3, 10, 12, generator=gen, dtype=torch.float64)
    weights = torch.rand(2, 10, 12, generator=gen, dtype=torch.float64)
    s = torch.tensor(src)

    def loss(dx, dz, lam):
        return (model(dn, s, pixel_size_um=dx, slice_spacing_um=dz, wavelength_um=lam) * weights).sum()

    params = tuple(torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in (0.4, 1.0, 0.6))
    assert torch.autograd.gradcheck(loss, params, eps=1e-7, atol=1e-6, rtol=1e-4)


def test_overrides_equal_to_defaults_change_nothing() -> None:
    model, src = _tiny_model()
    dn = 0.01 * torch.ones(3, 10, 12, dtype=torch.float64)
    s = torch.tensor(src)
    o = model.optics
    a = model(dn, s)
    b = model(dn, s, pixel_size_um=torch.tensor(o.pixel_size_um, dtype=torch.float64),
              slice_spacing_um=o.slice_spacing_um, wavelength_um=o.wavelength_um)
    assert torch.allclose(a, b, rtol=1e-12, atol=0)
