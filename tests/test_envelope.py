"""The coarse envelope model against the multi-slice model it approximates."""

from __future__ import annotations

import pytest
import torch

from napari_fdt.model.envelope import EnvelopeModel
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.optics import Optics
from napari_fdt.sim.phantoms import bead_phantom
from napari_fdt.sim.simulate import source_grid


@pytest.fixture(scope="module")
def scene():
    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=4, slice_spacing_um=2.0)
    src = source_grid(3, 8.0, 25.0)
    dn = bead_phantom((48, 48), 4, 0.33, 2.0, n_beads=6, radius_um=(1.0, 2.0), delta_n=0.01, rng=3)
    ms = MultiSliceModel(o, plan_for_sources(o, (48, 48), src), device="cpu", dtype=torch.float64)
    env = EnvelopeModel(o, (48, 48), 1, (0.0, 0.0), dtype=torch.float64)
    return o, torch.tensor(src), torch.tensor(dn, dtype=torch.float64), ms, env


def _rel(a, b, m):
    return float(torch.sqrt(((a - b) ** 2 * m).sum() / (b**2 * m).sum()))


def test_homogeneous_medium_matches_the_multislice_model(scene) -> None:
    o, src, dn, ms, env = scene
    zero = torch.zeros_like(dn)
    m = env.coverage(src)
    assert m.mean() > 0.9
    assert _rel(env(zero, src), ms(zero, src), m) < 0.03  # measured 0.017 on the bundled sample geometry


def test_weak_object_signal_matches_the_multislice_model(scene) -> None:
    """The change the sample makes to each image agrees with the exact model's to within the paraxial error."""
    o, src, dn, ms, env = scene
    zero = torch.zeros_like(dn)
    m = env.coverage(src)
    d_env = env(dn, src) - env(zero, src)
    d_ms = ms(dn, src) - ms(zero, src)
    assert _rel(d_env, d_ms, m) < 0.25


def test_window_is_a_fraction_of_the_multislice_window(scene) -> None:
    o, src, dn, ms, _ = scene
    coarse = EnvelopeModel(o, (12, 12), 4, (0.0, 0.0))
    assert coarse.padded[0] * coarse.padded[1] < 0.05 * ms.plan.padded_shape[0] * ms.plan.padded_shape[1]


def test_gradients_match_finite_differences() -> None:
    o = Optics(wavelength_um=0.6, n_background=1.33, na=0.6, pixel_size_um=0.8, n_slices=2, slice_spacing_um=1.0)
    env = EnvelopeModel(o, (8, 8), 2, (0.4, -0.4), dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    dn = (0.02 * torch.rand(2, 8, 8, generator=gen, dtype=torch.float64)).requires_grad_()
    src = torch.tensor([[0.3, -0.2, 6.0], [-0.5, 0.4, 7.0]], dtype=torch.float64, requires_grad=True)
    w = torch.rand(2, 8, 8, generator=gen, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda d, s: (env(d, s) * w).sum(), (dn, src), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_both_models_are_image_models(scene) -> None:
    """The interface of napari_fdt.model.protocol: shapes of images, and the optics overrides the solver passes."""
    from napari_fdt.model.protocol import ImageModel

    o, src, dn, ms, env = scene
    for model in (ms, env):
        assert isinstance(model, ImageModel)
        assert model.image_shape == (48, 48) and model.pixel_size_um == pytest.approx(0.33)
        out = model(dn, src[:2], torch.tensor([1.0, 2.0], dtype=torch.float64), slice_spacing_um=2.1, wavelength_um=0.64)
        assert out.shape == (2, 48, 48) and out.dtype == torch.float64


def test_envelope_step_is_the_angular_spectrum_kernel() -> None:
    """The envelope's Fresnel-scaled step is propagation_kernel over Δz·h0/h1 at frequency f_p/h0."""
    from napari_fdt.physics.propagation import propagation_kernel

    f2p = torch.linspace(0.0, 200.0, 101, dtype=torch.float64).reshape(1, 1, -1).expand(2, 1, -1)
    h0, h1 = torch.tensor([5.0, 9.0], dtype=torch.float64), torch.tensor([7.0, 9.5], dtype=torch.float64)
    k = EnvelopeModel._kernel(f2p, h0, h1, 1.33, 0.6)
    ref = propagation_kernel(f2p / (h0 * h0)[:, None, None], ((h1 - h0) * h0 / h1)[:, None, None], 1.33, 0.6)
    assert torch.allclose(k, ref, rtol=1e-12, atol=1e-14)
    assert k[0, 0, -1] == 0 and torch.allclose(k.abs()[..., :10], torch.ones(2, 1, 10, dtype=torch.float64))  # evanescent beyond n_b/λ, unit modulus below


def _scene_for_loop(dtype):
    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=5, slice_spacing_um=2.0)
    env = EnvelopeModel(o, (12, 12), 4, (0.5, -0.3), dtype=dtype)
    gen = torch.Generator().manual_seed(0)
    dn = (0.02 * torch.rand(5, 12, 12, generator=gen, dtype=torch.float64)).to(dtype).requires_grad_()
    src = torch.tensor([[1.0, 2.0, 30.0], [-3.0, 4.0, 28.0], [5.0, -6.0, 32.0]], dtype=dtype, requires_grad=True)
    dz = torch.tensor(2.05, dtype=dtype, requires_grad=True)
    gain = torch.tensor([1.0, 1.2, 0.9], dtype=dtype, requires_grad=True)
    return env, (dn, src, gain, dz)


def test_batched_path_equals_the_per_slice_loop_with_its_gradients() -> None:
    """All sources and slices in one batch (hand-written adjoint) = the one-slice-at-a-time loop under plain autograd."""
    env, (dn, src, gain, dz) = _scene_for_loop(torch.float64)
    a = env.images_batched(dn, src, gain, slice_spacing_um=dz)
    b = env.images_per_slice(dn, src, gain, slice_spacing_um=dz)
    assert float((a - b).norm() / b.norm()) < 1e-12
    w = torch.rand_like(a)
    ga = torch.autograd.grad((a * w).sum(), (dn, src, gain, dz))
    gb = torch.autograd.grad((b * w).sum(), (dn, src, gain, dz))
    for x, y in zip(ga, gb):
        assert float((x - y).norm() / y.norm()) < 1e-10


def test_envelope_loop_adjoint_against_gradcheck() -> None:
    """The hand-written adjoint of the loop, for complex screens and kernels (PyTorch's complex convention)."""
    from napari_fdt.model.envelope_loop import envelope_loop

    gen = torch.Generator().manual_seed(2)
    phase = torch.rand(3, 2, 6, 5, generator=gen, dtype=torch.float64).requires_grad_()
    kernels = (torch.randn(3, 2, 6, 5, generator=gen, dtype=torch.complex128) / 30).requires_grad_()
    assert torch.autograd.gradcheck(lambda p, k: envelope_loop(p, k).abs().square().sum(), (phase, kernels), eps=1e-6, atol=1e-7)
    kfixed = kernels.detach()
    assert torch.autograd.gradcheck(lambda p: envelope_loop(p, kfixed).real.sum(), (phase,), eps=1e-6, atol=1e-7)
    pfixed = phase.detach()
    assert torch.autograd.gradcheck(lambda k: envelope_loop(pfixed, k).imag.sum(), (kernels,), eps=1e-6, atol=1e-7)


def test_batched_path_float32_against_float64_reference() -> None:
    env32, args32 = _scene_for_loop(torch.float32)
    env64, args64 = _scene_for_loop(torch.float64)
    a = env32.images_batched(args32[0], args32[1], args32[2], slice_spacing_um=args32[3])
    b = env64.images_per_slice(args64[0], args64[1], args64[2], slice_spacing_um=args64[3])
    assert float((a.double() - b).norm() / b.norm()) < 1e-5


def test_step_kernels_match_the_autograd_kernels_with_gradients() -> None:
    """The hand-written backward of all step kernels = autograd through EnvelopeModel._kernels (float64)."""
    from napari_fdt.model.envelope_loop import step_kernels

    gen = torch.Generator().manual_seed(3)
    f2p = (3000.0 * torch.rand(1, 2, 6, 5, generator=gen, dtype=torch.float64)).requires_grad_()
    h0 = (20.0 + torch.rand(3, 2, generator=gen, dtype=torch.float64)).requires_grad_()
    h1 = (h0.detach() + 2.0).requires_grad_()
    wr = torch.randn(3, 2, 6, 5, generator=gen, dtype=torch.complex128)
    got = step_kernels(f2p, h0, h1, 1.33, 0.635, 0.5)
    ref = EnvelopeModel._kernels(f2p, h0, h1, 1.33, 0.635) * 0.5
    assert ((f2p / h0[:, :, None, None] ** 2) >= (1.33 / 0.635) ** 2).any()  # some evanescent entries are covered
    assert torch.allclose(got, ref, atol=1e-13)
    g_got = torch.autograd.grad((got * wr).real.sum(), (f2p, h0, h1))
    g_ref = torch.autograd.grad((ref * wr).real.sum(), (f2p, h0, h1))
    for a, b in zip(g_got, g_ref):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12)


def test_batched_is_the_default_and_graphs_need_cuda() -> None:
    from benchmarks._graphed import can_graph, graphed_model

    o = Optics(wavelength_um=0.6, n_background=1.33, na=0.6, pixel_size_um=0.8, n_slices=2, slice_spacing_um=1.0)
    assert EnvelopeModel(o, (8, 8), 2, (0.0, 0.0)).batched is True  # every device (the CPU measured faster too)
    assert EnvelopeModel(o, (8, 8), 2, (0.0, 0.0), device="cuda").batched is True  # nothing is allocated here
    assert EnvelopeModel(o, (8, 8), 2, (0.0, 0.0), batched="auto").batched is True
    assert EnvelopeModel(o, (8, 8), 2, (0.0, 0.0), batched=False).batched is False
    assert EnvelopeModel(o, (8, 8), 2, (0.0, 0.0), batched=True).batched is True
    with pytest.raises(ValueError, match="batched"):
        EnvelopeModel(o, (8, 8), 2, (0.0, 0.0), batched="yes")
    cpu = EnvelopeModel(o, (8, 8), 2, (0.0, 0.0))
    assert can_graph("cpu") is False
    with pytest.raises(ValueError, match="CUDA"):
        graphed_model(cpu, torch.zeros(2, 8, 8), torch.zeros(1, 3), torch.ones(1))


@pytest.mark.parametrize("factor", [1, 2, 4])
def test_fft_window_sides_are_smooth_and_hold_the_padding(factor) -> None:
    """Each side of the envelope's FFT window is even and 2·3·5-smooth (pocketfft: 74 = 2·37 points cost 5.7× 80), at
    least the grid plus the light cone's padding on both sides; the plan's cost model prices the model's own window."""
    from napari_fdt.model.envelope import envelope_window, padding_px
    from napari_fdt.recon.loop.step_cost import envelope_padded_shape

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=8, slice_spacing_um=2.0)
    pad = padding_px(o, factor)
    for grid in [(24, 24), (37, 29), (96 // factor, 128 // factor)]:
        sides, lead = envelope_window(o, grid, factor)
        for side, n, before in zip(sides, grid, lead):
            m = side
            for p in (2, 3, 5):
                while m % p == 0:
                    m //= p
            assert m == 1 and side % 2 == 0
            assert before >= pad and side - n - before >= pad and side - n - 2 * pad < 2 * (n + 2 * pad) // 10 + 2
        model = EnvelopeModel(o, grid, factor, (0.0, 0.0))
        assert model.padded == sides and model.lead == lead
        assert envelope_padded_shape(o, (grid[0] * factor, grid[1] * factor), factor) == sides
