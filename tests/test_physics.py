"""The forward model against physics: free space, the analytic point source, first Born, a lens.

Every reference here is computed independently of the multi-slice loop (analytic fields, a single
free-space propagation, or the Born integral with the Green's function's angular spectrum).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.grid import frequency_grid, plan_for_sources
from napari_fdt.physics.optics import Optics
from napari_fdt.physics.propagation import propagation_kernel, pupil


def _optics(**kw) -> Optics:
    base = dict(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.25, n_slices=4,
                slice_spacing_um=1.5, image_plane_um=0.0)
    base.update(kw)
    return Optics(**base)


def _window_coords(model: MultiSliceModel) -> tuple[np.ndarray, np.ndarray]:
    hp, wp = model.plan.padded_shape
    dx = model.optics.pixel_size_um
    y = (np.arange(hp) - hp // 2)[:, None] * dx
    x = (np.arange(wp) - wp // 2)[None, :] * dx
    return y, x


@pytest.mark.parametrize("depth_um", [30.0, 100.0])
def test_point_source_matches_spherical_wave(depth_um: float) -> None:
    """The spectral source equals d·exp(ik(R−z))/R inside the pupil's cone (PHYSICS.md: few %)."""
    opt = _optics(n_slices=1, slice_spacing_um=1.0)
    src = np.array([[2.0, -3.0, depth_um]])
    model = MultiSliceModel(opt, plan_for_sources(opt, (96, 96), src), device="cpu", dtype=torch.float64)
    u = torch.fft.ifft2(model.source_spectrum(torch.tensor(src))).numpy()[0]
    y, x = _window_coords(model)
    z = depth_um + 0.5 * opt.slice_spacing_um  # the first screen's plane
    rho = np.hypot(x - 2.0, y + 3.0)
    r = np.sqrt(rho**2 + z**2)
    k = 2 * np.pi * opt.n_background / opt.wavelength_um
    analytic = depth_um * np.exp(1j * k * (r - z)) / r
    s = opt.na / opt.n_background
    cone = z * s / math.sqrt(1 - s * s)
    # The plan guarantees the field over the image and its light-cone margin, not the whole window.
    reach = 48 * opt.pixel_size_um + model.plan.margin_um
    inside = (np.abs(x) <= reach) & (np.abs(y) <= reach)
    for frac, tol in ((0.5, 0.01), (0.7, 0.05)):
        m = inside & (rho < frac * cone)
        rel = np.sqrt(np.mean(np.abs(u[m] - analytic[m]) ** 2) / np.mean(np.abs(analytic[m]) ** 2))
        assert rel < tol, (frac, rel)
    # The spot is centred on the source: centroid of |u|^2 over a disc around the true position.
    m = rho < 0.5 * min(cone, reach - 4.0)
    wgt = np.abs(u[m]) ** 2
    assert abs((wgt * x.repeat(u.shape[0], 0)[m]).sum() / wgt.sum() - 2.0) < 0.02
    assert abs((wgt * y.repeat(u.shape[1], 1)[m]).sum() / wgt.sum() + 3.0) < 0.02


def test_image_centroid_sits_under_source() -> None:
    """The defocused disc of a source seen through a homogeneous volume is centred on (x_s, y_s)."""
    opt = _optics(na=0.5)
    src = np.array([[1.37, -2.11, 20.0]])
    model = MultiSliceModel(opt, plan_for_sources(opt, (128, 128), src), device="cpu", dtype=torch.float64)
    img = model(torch.zeros(opt.n_slices, 128, 128, dtype=torch.float64), torch.tensor(src))[0].numpy()
    yy = (np.arange(128) - 64)[:, None] * opt.pixel_size_um
    xx = (np.arange(128) - 64)[None, :] * opt.pixel_size_um
    total = img.sum()
    assert abs((img * xx).sum() / total - 1.37) < 0.05
    assert abs((img * yy).sum() / total + 2.11) < 0.05


@pytest.mark.parametrize("image_plane_um", [0.0, 2.5])
def test_homogeneous_volume_is_free_space(image_plane_um: float) -> None:
    """Zero or uniform contrast gives the images of one free-space propagation over the whole distance."""
    opt = _optics(image_plane_um=image_plane_um)
    src = np.array([[0.5, 1.0, 25.0], [-4.0, 3.0, 35.0]])
    model = MultiSliceModel(opt, plan_for_sources(opt, (64, 80), src), device="cpu", dtype=torch.float64)
    s = torch.tensor(src)
    # Reference: the source spectrum at the first screen, one propagation to the focal plane, pupil.
    fy, fx = frequency_grid(model.plan.padded_shape, opt.pixel_size_um, dtype=torch.float64)
    f2 = fy**2 + fx**2
    rest = opt.thickness_um - 0.5 * opt.slice_spacing_um - image_plane_um
    spec = model.source_spectrum(s) * propagation_kernel(f2, rest, opt.n_background, opt.wavelength_um)
    ref = model.crop(torch.fft.ifft2(spec * pupil(f2, opt.na, opt.wavelength_um, model.plan.pupil_taper))).abs().square()
    zero = model(torch.zeros(opt.n_slices, 64, 80, dtype=torch.float64), s)
    hp, wp = model.plan.padded_shape
    uniform = model(torch.full((opt.n_slices, hp, wp), 0.02, dtype=torch.float64), s)
    scale = ref.max()
    assert torch.allclose(zero, ref, atol=1e-10 * scale)
    assert torch.allclose(uniform, ref, atol=1e-9 * scale)


def _born_reference(model: MultiSliceModel, phase_object: np.ndarray, src: np.ndarray, sub: int = 16) -> np.ndarray:
    """First-Born camera field of a thin slab in slice 0: Green's function angular spectrum, slab integrated in z.

    ∇²U + k²U = −V·U, V = k0²(n² − n_b²) ≈ 2·k0²·n_b·Δn; G = e^{ikR}/(4πR) ↔ (i/(4π qz))·e^{i2π qz z}.
    """
    opt = model.optics
    dz = opt.slice_spacing_um
    fy, fx = frequency_grid(model.plan.padded_shape, opt.pixel_size_um, dtype=torch.float64)
    f2 = (fy**2 + fx**2)
    k_b = opt.n_background / opt.wavelength_um
    prop = f2 < k_b**2
    qz = torch.sqrt(torch.clamp(k_b**2 - f2, min=1e-30))
    dn = model.pad_volume(torch.tensor(phase_object, dtype=torch.float64))[0]
    k0 = 2 * math.pi / opt.wavelength_um
    v = 2 * k0**2 * opt.n_background * dn
    s = torch.tensor(src, dtype=torch.float64)
    scattered = torch.zeros(model.plan.padded_shape, dtype=torch.complex128)
    h = dz / sub
    for j in range(sub):  # midpoint rule over the slab [0, dz]
        zj = (j + 0.5) * h
        # incident field at height zj above the bottom face (first screen is at dz/2)
        u_in = torch.fft.ifft2(model.source_spectrum(s)[0] * propagation_kernel(f2, zj - 0.5 * dz, opt.n_background, opt.wavelength_um))
        src_spec = torch.fft.fft2(v * u_in) * h
        # propagate to the top face of a one-slice volume (z = dz), envelope convention
        green = torch.where(prop, 1j / (4 * math.pi * qz), 0)  # discrete: ifft2(Ĝ·fft2(·)) = ∫G(r−r')·(·)(r')dr'
        scattered = scattered + src_spec * green * propagation_kernel(f2, dz - zj, opt.n_background, opt.wavelength_um)
    # Born scattered field at the top face, then the camera path (focal plane at the top face here).
    out = torch.fft.ifft2(scattered * pupil(f2, opt.na, opt.wavelength_um, model.plan.pupil_taper))
    return model.crop(out).numpy()


@pytest.mark.parametrize("na,tol", [(0.3, 0.02)])
def test_weak_phase_object_matches_first_born(na: float, tol: float) -> None:
    """A weak thin object: multi-slice scattered field = first-Born scattered field (paraxial optics)."""
    opt = _optics(na=na, n_slices=1, slice_spacing_um=0.5, pixel_size_um=0.3)
    h = w = 64
    yy, xx = np.mgrid[:h, :w]
    blob = np.exp(-(((yy - 30) ** 2 + (xx - 36) ** 2) / (2 * 3.0**2)))
    obj = (1e-3 * blob)[None]  # phase ≈ 2π/λ·Δz·Δn ≈ 5e-3 rad
    src = np.array([[0.0, 0.0, 15.0]])
    model = MultiSliceModel(opt, plan_for_sources(opt, (h, w), src), device="cpu", dtype=torch.float64)
    s = torch.tensor(src)
    e_obj = model.camera_field(torch.tensor(obj), s).numpy()[0]
    e_0 = model.camera_field(torch.zeros_like(torch.tensor(obj)), s).numpy()[0]
    ms_scattered = e_obj - e_0
    born = _born_reference(model, obj, src)
    rel = np.linalg.norm(ms_scattered - born) / np.linalg.norm(born)
    assert rel < tol, rel


@pytest.mark.parametrize("sign,image_plane_um,bound", [(+1, -20.0, 2.0), (-1, -40.0, 0.6)])
def test_higher_index_bead_focuses_light(sign: int, image_plane_um: float, bound: float) -> None:
    """A bead of higher index than the medium is a converging lens: a bright spot above it; a lower index spreads."""
    opt = _optics(na=0.8, n_slices=10, slice_spacing_um=1.0, pixel_size_um=0.25, image_plane_um=image_plane_um)
    h = w = 96
    dx = opt.pixel_size_um
    zc = (np.arange(opt.n_slices) + 0.5) * opt.slice_spacing_um
    yy, xx = (np.mgrid[:h, :w] - h // 2) * dx
    r = np.sqrt(xx[None] ** 2 + yy[None] ** 2 + (zc[:, None, None] - 5.0) ** 2)
    bead = sign * 0.03 * np.clip(3.0 - r + 0.5, 0, 1)  # radius 3 µm, soft edge, centre 5 µm above the bottom
    src = np.array([[0.0, 0.0, 100.0]])
    model = MultiSliceModel(opt, plan_for_sources(opt, (h, w), src), device="cpu", dtype=torch.float64)
    s = torch.tensor(src)
    with_bead = model(torch.tensor(bead), s)[0].numpy()
    without = model(torch.zeros(opt.n_slices, h, w, dtype=torch.float64), s)[0].numpy()
    c = slice(h // 2 - 2, h // 2 + 2)
    ratio = with_bead[c, c].mean() / without[c, c].mean()
    if sign > 0:
        assert ratio > bound, ratio
    else:
        assert ratio < bound, ratio


def test_planned_window_is_large_enough() -> None:
    """Images on the geometry-derived window agree with those on a window 2.4x wider (no wrap-around)."""
    import dataclasses

    opt = _optics(na=0.8, n_slices=6, slice_spacing_um=2.0, pixel_size_um=0.33, image_plane_um=1.0)
    h = w = 48
    src = np.array([[-4.0, 5.0, 30.0], [6.0, -6.0, 35.0]])
    plan = plan_for_sources(opt, (h, w), src)
    yy, xx = np.mgrid[:h, :w]
    dn = np.zeros((opt.n_slices, h, w))
    dn[2] = 0.03 * np.exp(-((yy - 20) ** 2 + (xx - 28) ** 2) / 50.0)
    big = 2 * next_fast_even_ge(int(1.2 * plan.padded_shape[0]) // 2)
    wide = dataclasses.replace(plan, padded_shape=(big, big), offset=(big // 2 - h // 2, big // 2 - w // 2))
    s, d = torch.tensor(src), torch.tensor(dn)
    a = MultiSliceModel(opt, plan, device="cpu", dtype=torch.float64)(d, s)
    b = MultiSliceModel(opt, wide, device="cpu", dtype=torch.float64)(d, s)
    rel = float(torch.linalg.norm(a - b) / torch.linalg.norm(b))
    assert rel < 2e-3, (plan.padded_shape, big, rel)


def next_fast_even_ge(n: int) -> int:
    from napari_fdt.physics.grid import next_fast_even

    return next_fast_even(2 * n) // 2


def test_the_phasor_is_exp_i_phase_with_its_gradient() -> None:
    """``phasor`` (cos and sin on the CPU, where torch's polar kernel is slow) against numpy's ``m·exp(iφ)``, float32
    and float64, and its gradient in the phase and a signed magnitude against torch's numerical one."""
    from napari_fdt.physics.propagation import phasor

    rng = np.random.default_rng(0)
    phase = rng.uniform(-40, 40, (3, 5))
    mag = rng.uniform(-2, 2, (3, 5))
    for dtype, tol in ((torch.float32, 1e-5), (torch.float64, 1e-14)):
        got = phasor(torch.tensor(phase, dtype=dtype), torch.tensor(mag, dtype=dtype)).numpy()
        assert np.abs(got - mag * np.exp(1j * phase)).max() < tol * 2
        assert np.abs(phasor(torch.tensor(phase, dtype=dtype)).numpy() - np.exp(1j * phase)).max() < tol
    p = torch.tensor(phase, dtype=torch.float64, requires_grad=True)
    m = torch.tensor(mag, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(phasor, (p, m))


def test_an_absurd_focal_plane_or_depth_is_capped_or_refused_at_once() -> None:
    """A focal plane 4e15 µm away (a corrupted acquisition.json: hypothesis found it) caps the window with a warning,
    and sources 1e15 µm deep are refused, both without searching 5-smooth sizes near 1e16 px (which hung `fdt info`)."""
    import warnings

    from napari_fdt.errors import FDTInputError
    from napari_fdt.physics.grid import MAX_PADDED_SIDE, plan_grid

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=4, slice_spacing_um=2.0,
               image_plane_um=-4.0e15)
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        plan = plan_grid(o, (16, 16), (1.0, 1.0), 20.0)
    assert max(plan.padded_shape) == MAX_PADDED_SIDE
    with pytest.raises(FDTInputError, match="window"):
        plan_grid(Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=4, slice_spacing_um=2.0),
                  (16, 16), (1.0, 1.0), 1.0e15)
