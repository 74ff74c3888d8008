"""The split-field model (``model.split_field``): the sources' field exact and non-periodic, the sample's on a window of
the image and its light cone. Held against the independent reference (tests/independent_reference.py, float64, numpy)
on a window twice as wide as the plan's, where the periodic copies are far: the converged answer both models
approximate."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from napari_fdt import Optics
from napari_fdt.errors import FDTInputError
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.split_field import SplitFieldModel, split_plan
from napari_fdt.physics.grid import plan_for_sources
from tests import independent_reference as ref
from tests.test_sub_slices import OPTICS, _rel, _scene  # a 32² bead (Δn 0.04), 3 sources 15-18 µm deep, NA 0.8


def _setup():
    dn, src = _scene()
    o = Optics(**OPTICS)
    return dn, src, o, plan_for_sources(o, dn.shape[1:], src, warn=False)


def _images(model, dn, src) -> np.ndarray:
    with torch.no_grad():
        return model(torch.from_numpy(dn), torch.from_numpy(src)).numpy()


def _wide_reference(dn, src, plan) -> np.ndarray:
    (hp, wp), (h, w) = plan.padded_shape, plan.image_shape
    window = {"Hp": 2 * hp, "Wp": 2 * wp, "offset_y": hp - h // 2, "offset_x": wp - w // 2}
    return ref.forward_images(OPTICS, OPTICS["n_background"] + dn, src, np.ones(len(src)), window=window)


def test_the_split_window_holds_the_image_and_its_light_cone_and_is_smaller() -> None:
    dn, src, o, plan = _setup()
    small = split_plan(plan, o)
    for n, p, s in zip(plan.image_shape, plan.padded_shape, small.padded_shape):
        assert s < p and s % 2 == 0
        assert (s - n) / 2 * o.pixel_size_um >= plan.margin_um  # the cone's margin on each side
    assert small.offset == (small.padded_shape[0] // 2 - 16, small.padded_shape[1] // 2 - 16)


def test_the_split_model_is_as_close_to_the_converged_answer_as_the_full_window() -> None:
    dn, src, o, plan = _setup()
    truth = _wide_reference(dn, src, plan)
    full = _rel(_images(MultiSliceModel(o, plan, device="cpu", dtype=torch.float64), dn, src), truth)
    split = _rel(_images(SplitFieldModel(o, plan, device="cpu", dtype=torch.float64), dn, src), truth)
    print(f"full window {full:.2e}, split {split:.2e}")
    assert split < 3e-4  # measured 1.8e-4 (the full window: 1.8e-3, its periodic copies' pupil tails)
    assert split < full


def test_the_sources_field_at_every_screen_is_the_propagated_point_source() -> None:
    """The radial tables against FFT propagation of the band-limited source on a window twice the plan's (its copies'
    roll-off far from the image: on the plan's own window they differ by 2.6e-4)."""
    dn, src, o, plan = _setup()
    split = SplitFieldModel(o, plan, device="cpu", dtype=torch.float64)
    (hp, wp), (h, w) = plan.padded_shape, plan.image_shape
    wide = dataclasses.replace(plan, padded_shape=(2 * hp, 2 * wp), offset=(hp - h // 2, wp - w // 2))
    full = MultiSliceModel(o, wide, device="cpu", dtype=torch.float64)
    k = full.kernels()
    u = torch.fft.ifft2(full.source_spectrum(torch.from_numpy(src), k))
    expected = []
    for i in range(o.n_slices):
        if i:
            u = torch.fft.ifft2(torch.fft.fft2(u) * k.slice_kernel)
        expected.append(full.crop(u))
    expected = torch.stack(expected, 1)
    got = split.incident_fields(torch.from_numpy(src))
    assert got.shape == expected.shape
    assert float(torch.linalg.norm(got - expected) / torch.linalg.norm(expected)) < 1e-4  # measured 3e-5


@pytest.mark.parametrize("options", [
    {"pixel_integration": True},
    {"sub_slices": 2},
    {"aberrations": {"spherical": 0.5}},
    {"aberrations": {"coma_horizontal": 0.4, "defocus": 0.3}},  # a non-radial phase: the full window's free field
    {"obliquity": "per_source"},  # each source's screens scaled by 1/cos θ of its rays (measured 2.0e-4)
    {"obliquity": "per_source", "sub_slices": 2},  # measured 1.2e-4
])
def test_the_model_parts_agree_with_a_wide_full_window(options) -> None:
    """Against the full-window model on twice the plan's window (converged: the plan's own is 1-2e-3 off here)."""
    dn, src, o, plan = _setup()
    (hp, wp), (h, w) = plan.padded_shape, plan.image_shape
    wide = dataclasses.replace(plan, padded_shape=(2 * hp, 2 * wp), offset=(hp - h // 2, wp - w // 2))
    full = _images(MultiSliceModel(o, wide, device="cpu", dtype=torch.float64, **options), dn, src)
    split = _images(SplitFieldModel(o, plan, device="cpu", dtype=torch.float64, **options), dn, src)
    if "coma_horizontal" in options.get("aberrations", {}):  # the camera's free field from the plan's window: as good
        planned = _images(MultiSliceModel(o, plan, device="cpu", dtype=torch.float64, **options), dn, src)
        assert _rel(split, full) < 1.2 * _rel(planned, full)
    else:
        assert _rel(split, full) < 5e-4


def test_the_obliquity_screens_are_the_full_windows_not_the_thin_screens() -> None:
    """The per-source screens on the split window hold the full-window model's obliquity screens (wide window), ten
    times closer than the same split model without them: the test sees the correction, not only the window."""
    dn, src, o, plan = _setup()
    (hp, wp), (h, w) = plan.padded_shape, plan.image_shape
    wide = dataclasses.replace(plan, padded_shape=(2 * hp, 2 * wp), offset=(hp - h // 2, wp - w // 2))
    full = _images(MultiSliceModel(o, wide, device="cpu", dtype=torch.float64, obliquity="per_source"), dn, src)
    split = _images(SplitFieldModel(o, plan, device="cpu", dtype=torch.float64, obliquity="per_source"), dn, src)
    thin = _images(SplitFieldModel(o, plan, device="cpu", dtype=torch.float64), dn, src)
    assert _rel(split, full) < 0.1 * _rel(thin, full)  # measured 2.0e-4 against 1.4e-2
    secants = SplitFieldModel(o, plan, device="cpu", dtype=torch.float64).screen_secants(torch.from_numpy(src))
    assert secants.shape == (len(src), o.n_slices, h, w) and float(secants.min()) >= 1.0


@pytest.mark.parametrize("obliquity", ["none", "per_source"])
def test_gradients_are_those_of_the_images(obliquity) -> None:
    """Finite differences of a loss in the contrast, a source's position and depth, the pixel and the wavelength
    (with the obliquity screens: their secants move with the sources)."""
    dn, src, o, plan = _setup()
    model = SplitFieldModel(o, plan, device="cpu", dtype=torch.float64, obliquity=obliquity)
    target = torch.from_numpy(_images(model, 1.1 * dn, src))

    def loss(d, s, dx, lam):
        return (model(d, s, pixel_size_um=dx, wavelength_um=lam) - target).square().sum()

    d = torch.from_numpy(dn).requires_grad_(True)
    s = torch.from_numpy(src).requires_grad_(True)
    dx = torch.tensor(o.pixel_size_um, dtype=torch.float64, requires_grad=True)
    lam = torch.tensor(o.wavelength_um, dtype=torch.float64, requires_grad=True)
    loss(d, s, dx, lam).backward()
    checks = [
        ("contrast", d.grad[1, 15, 17], lambda e: (d.detach() + e * _unit(d, (1, 15, 17)), s.detach(), dx.detach(), lam.detach())),
        ("x", s.grad[1, 0], lambda e: (d.detach(), s.detach() + e * _unit(s, (1, 0)), dx.detach(), lam.detach())),
        ("depth", s.grad[2, 2], lambda e: (d.detach(), s.detach() + e * _unit(s, (2, 2)), dx.detach(), lam.detach())),
        ("pixel", dx.grad, lambda e: (d.detach(), s.detach(), dx.detach() + e, lam.detach())),
        ("wavelength", lam.grad, lambda e: (d.detach(), s.detach(), dx.detach(), lam.detach() + e)),
    ]
    for name, analytic, at in checks:
        eps = 1e-5
        with torch.no_grad():
            numeric = (loss(*at(eps)) - loss(*at(-eps))) / (2 * eps)
        assert float(abs(analytic - numeric)) < 2e-3 * float(abs(numeric)) + 1e-9, (name, float(analytic), float(numeric))


def test_the_screens_written_out_backward_is_autograds() -> None:
    """The screen on the window (``_ScreenUpdate``: S + (t − 1)·(S + U) on the image, its backward written out) against
    torch's numerical gradients, complex, in S, t − 1 and U."""
    from napari_fdt.model.split_field import _ScreenUpdate

    g = torch.Generator().manual_seed(0)

    def rand(*shape):
        return torch.complex(torch.randn(*shape, generator=g, dtype=torch.float64),
                             torch.randn(*shape, generator=g, dtype=torch.float64)).requires_grad_(True)

    s, u = rand(2, 7, 8), rand(2, 3, 4)
    for c in (rand(3, 4), rand(2, 3, 4)):  # one screen for all sources; one per source (the obliquity screens)
        # the update is in place: it gets a copy of S, as the model's loop gives it a fresh field
        assert torch.autograd.gradcheck(lambda s, c, u: _ScreenUpdate.apply(s * 1.0, c, u, 2, 3), (s, c, u))
        expected = s.detach().clone()
        expected[:, 2:5, 3:7] += c.detach() * (expected[:, 2:5, 3:7] + u.detach())
        assert torch.equal(_ScreenUpdate.apply(s.detach().clone(), c.detach(), u.detach(), 2, 3), expected)


def test_the_propagators_adjoint_is_autograds() -> None:
    """The step between screens with a constant kernel (``_Propagator``: its backward the same map with conj(K))
    against torch's numerical gradient, and its values against plain FFTs."""
    from napari_fdt.model.split_field import _Propagator

    g = torch.Generator().manual_seed(1)
    kernel = torch.exp(1j * torch.rand(6, 8, generator=g, dtype=torch.float64) * 6)
    s = torch.randn(3, 6, 8, generator=g, dtype=torch.complex128).requires_grad_(True)
    prop = _Propagator(kernel)
    assert torch.autograd.gradcheck(prop, (s,))
    assert torch.allclose(prop(s), torch.fft.ifft2(torch.fft.fft2(s) * kernel), atol=1e-14)


def test_the_tables_lookup_written_out_backward_is_autograds() -> None:
    """The radial tables' lookup (``_Lookup``: a linear interpolation times the carrier exp(i·2πk·(√(ρ²+H²) − H)), its
    backward written out) against torch's numerical gradients in the table, the radii, the heights and k, and its
    values against the formula; radii beyond the table's end take its last entry."""
    from napari_fdt.model.split_field import _Lookup

    g = torch.Generator().manual_seed(2)
    table = torch.randn(2, 3, 12, generator=g, dtype=torch.complex128).requires_grad_(True)
    rho = (torch.rand(2, 9, generator=g, dtype=torch.float64) * 1.3).requires_grad_(True)  # some past the end (1.1)
    heights = (2 + torch.rand(2, 3, generator=g, dtype=torch.float64)).requires_grad_(True)
    k = torch.tensor(2.1, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda *a: _Lookup.apply(*a, 0.1), (table, rho, heights, k))
    x = (rho.detach() / 0.1).clamp(max=11.0)
    i0 = x.floor().clamp(max=10).long()
    t = (x - i0)[:, None, :]
    idx = i0[:, None, :].expand(2, 3, -1)
    tab = table.detach()
    value = torch.gather(tab, 2, idx) * (1 - t) + torch.gather(tab, 2, idx + 1) * t
    r = torch.sqrt(rho.detach()[:, None, :] ** 2 + heights.detach()[..., None] ** 2)
    expected = value * torch.exp(2j * torch.pi * 2.1 * (r - heights.detach()[..., None]))
    assert torch.allclose(_Lookup.apply(tab, rho.detach(), heights.detach(), k.detach(), 0.1), expected, atol=1e-13)


def _unit(t: torch.Tensor, index: tuple) -> torch.Tensor:
    u = torch.zeros_like(t.detach())
    u[index] = 1.0
    return u


def test_the_solver_uses_it_where_it_holds() -> None:
    from napari_fdt.recon.problem.stages import uses_split_field

    assert uses_split_field("split", "cpu", 1, 0.4) and uses_split_field("split", "cuda", 1, 1.0)  # as the user says
    assert not uses_split_field("full", "cpu", 1, 0.4)
    assert uses_split_field("auto", "cpu", 1, 0.4)
    assert not uses_split_field("auto", "cpu", 1, 0.9)  # a window the light cone fills: nothing to save
    assert not uses_split_field("auto", "cuda", 1, 0.4)  # not measured on CUDA
    # the 2x field grid: split where the camera takes point samples of an image of even sizes (fine pixel 2i is
    # camera pixel i), the full window for pixel means (tests/test_field_oversampling.py holds the split one)
    assert uses_split_field("split", "cpu", 1, 0.4, field_oversampling=2, image_shape=(32, 32))
    assert not uses_split_field("split", "cpu", 1, 0.4, field_oversampling=2, image_shape=(32, 33))
    assert not uses_split_field("split", "cpu", 1, 0.4, field_oversampling=2, pixel_integration=True, image_shape=(32, 32))
    assert not uses_split_field("split", "cpu", 1, 0.4, pupil_edge=0.0)  # a hard pupil's tails wrap on the small window
    assert uses_split_field("split", "cpu", 1, 0.4, pupil_edge=0.05)
    dn, src, o, plan = _setup()
    with pytest.raises(FDTInputError, match="obliquity"):
        SplitFieldModel(o, plan, device="cpu", obliquity="per_ray")


def test_a_sample_that_is_not_there_adds_no_field() -> None:
    """Δn ≡ 0 (a constant the loop would multiply by 1): the sample's field S is zero, so the images are the
    homogeneous medium's, as the independent reference gives them for a volume of n_b alone (the pupil pilot's model,
    ``recon/choices/parts_pilot.py``, relies on it to skip the slice loop)."""
    dn, src, o, plan = _setup()
    zero = np.zeros_like(dn)
    model = SplitFieldModel(o, plan, device="cpu", dtype=torch.float64)
    spec, _ = model.exit_spectra(torch.from_numpy(zero), torch.from_numpy(src))
    assert spec.shape[-2:] == model.plan.padded_shape and not bool(spec.any())
    assert _rel(_images(model, zero, src), _wide_reference(zero, src, plan)) < 3e-4
