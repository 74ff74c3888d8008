"""Pixel integration, the pupil edge and the Zernike convention against definitions and physics."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from napari_fdt.errors import FDTInputError
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.aberrations import parse_aberrations, zernike_phase
from napari_fdt.physics.camera import needs_pixel_integration, pixel_averaged_intensity, resolve_pixel_integration
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.optics import Optics
from napari_fdt.recon.problem.stages import camera_model_options
from napari_fdt.recon.settings.config import SolverConfig


def test_pixel_average_matches_numerical_integration() -> None:
    """The Fourier-domain pixel mean equals the pixel mean by a 32×32-point trapezoid rule over the area."""
    torch.manual_seed(0)
    h, w, k = 24, 30, 32
    fy = torch.fft.fftfreq(h).reshape(-1, 1)
    fx = torch.fft.fftfreq(w).reshape(1, -1)
    spec = torch.randn(h, w, dtype=torch.complex128) * ((fy**2 + fx**2) < 0.24**2)
    ours = pixel_averaged_intensity(spec[None])[0]
    big = torch.fft.fftshift(spec)
    big = torch.nn.functional.pad(big, ((k - 1) * w // 2, (k - 1) * w // 2, (k - 1) * h // 2, (k - 1) * h // 2))
    fine = torch.fft.ifft2(torch.fft.ifftshift(big)) * k * k  # the field on dx/k
    inten = torch.roll(fine.abs() ** 2, (k // 2, k // 2), (0, 1))
    inten = torch.cat([inten, inten[:1]], 0)
    inten = torch.cat([inten, inten[:, :1]], 1)
    wts = torch.ones(k + 1, dtype=torch.float64)
    wts[0] = wts[-1] = 0.5
    wts /= k
    ref = sum(wts[a] * wts[b] * inten[a::k][:h, b::k][:, :w] for a in range(k + 1) for b in range(k + 1))
    point = torch.fft.ifft2(spec).abs() ** 2
    assert float((ours - ref).norm() / ref.norm()) < 5e-4
    assert float((point - ref).norm() / ref.norm()) > 0.03  # the effect is real at this band


def test_the_pixel_mean_on_real_transforms_is_the_whole_grids_fourier_formula() -> None:
    """``pixel_average_from_fine`` (real transforms, one axis at a time, folded early) against the formula on the whole
    fine grid's complex spectrum: fft2 of |E|², times sinc(fx·dx)·sinc(fy·dx), the four quadrants' mean, ifft2; and
    its gradient against torch's numerical one."""
    from napari_fdt.physics.camera import pixel_average_from_fine

    g = torch.Generator().manual_seed(3)
    fine = torch.randn(2, 20, 28, generator=g, dtype=torch.complex128)
    inten = fine.abs() ** 2
    spec = torch.fft.fft2(inten)
    ty = torch.sinc(torch.fft.fftfreq(20, dtype=torch.float64) * 2.0).reshape(-1, 1)
    tx = torch.sinc(torch.fft.fftfreq(28, dtype=torch.float64) * 2.0).reshape(1, -1)
    spec = spec * ty * tx
    folded = (spec[..., :10, :14] + spec[..., 10:, :14] + spec[..., :10, 14:] + spec[..., 10:, 14:]) / 4
    reference = torch.fft.ifft2(folded).real
    assert float((pixel_average_from_fine(fine) - reference).abs().max() / reference.abs().max()) < 1e-13
    small = torch.randn(1, 8, 12, generator=g, dtype=torch.complex128).requires_grad_(True)
    assert torch.autograd.gradcheck(pixel_average_from_fine, (small,))


def test_auto_rule_is_the_nyquist_of_the_intensity() -> None:
    assert needs_pixel_integration(0.8, 0.635, 0.33)  # 2.52 /µm > 1.52 /µm
    assert not needs_pixel_integration(0.3, 0.635, 0.33)  # 0.94 < 1.52
    assert resolve_pixel_integration("auto", 0.3, 0.635, 0.33) is False
    assert resolve_pixel_integration(True, 0.3, 0.635, 0.33) is True
    with pytest.raises(FDTInputError, match="pixel_integration"):
        resolve_pixel_integration("maybe", 0.3, 0.635, 0.33)


def test_camera_options_follow_the_acquisition() -> None:
    optics = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=2, slice_spacing_um=1.0)
    cfg = SolverConfig()
    real = SimpleNamespace(optics=optics, extra={})
    old_sim = SimpleNamespace(optics=optics, extra={"simulated": {}})
    new_sim = SimpleNamespace(optics=optics, extra={"simulated": {}, "pixel_integration": True, "pupil_edge": 0.0})
    assert camera_model_options(cfg, real) == {"pupil_edge": 0.03, "pixel_integration": True}
    assert camera_model_options(cfg, old_sim) == {"pupil_edge": 0.03, "pixel_integration": False}
    assert camera_model_options(cfg, new_sim) == {"pupil_edge": 0.0, "pixel_integration": True}
    assert camera_model_options(SolverConfig(pixel_integration="false", pupil_edge=0.01), new_sim) == {"pupil_edge": 0.01, "pixel_integration": False}
    with pytest.raises(FDTInputError, match="pupil_edge"):
        camera_model_options(cfg, SimpleNamespace(optics=optics, extra={"pupil_edge": "hard"}))


def test_zernike_modes_are_noll_normalised() -> None:
    """Each mode has RMS 1 over the unit disc and the documented form at a few points."""
    n = 801
    c = torch.linspace(-1, 1, n, dtype=torch.float64)
    fy, fx = c.reshape(-1, 1), c.reshape(1, -1)
    inside = (fy**2 + fx**2) <= 1
    for j in range(6):
        coeffs = torch.zeros(6, dtype=torch.float64)
        coeffs[j] = 1.0
        z = zernike_phase(fy, fx, 1.0, 1.0, coeffs)
        assert float(z[inside].square().mean().sqrt()) == pytest.approx(1.0, abs=5e-3)
    one = torch.tensor([[1.0]], dtype=torch.float64)
    zero = torch.tensor([[0.0]], dtype=torch.float64)
    # coma_vertical at (fx, fy) = (0, 1): √8·(3 − 2)·sin 90° = √8; astigmatism_vertical at (1, 0): √6
    assert float(zernike_phase(one, zero, 1.0, 1.0, [0, 0, 0, 1, 0, 0])) == pytest.approx(math.sqrt(8))
    assert float(zernike_phase(zero, one, 1.0, 1.0, [0, 0, 1, 0, 0, 0])) == pytest.approx(math.sqrt(6))
    assert parse_aberrations("spherical=0.5, defocus=-0.2") == {"spherical": 0.5, "defocus": -0.2}
    with pytest.raises(FDTInputError, match="aberrations"):
        parse_aberrations("trefoil=1")


def test_defocus_mode_moves_the_focal_plane_as_documented() -> None:
    """A positive defocus c acts like image_plane_um larger by 2√3·c·n_b·λ/(π·NA²) (paraxial: low NA)."""
    base = dict(wavelength_um=0.6, n_background=1.33, na=0.25, pixel_size_um=0.5, n_slices=2, slice_spacing_um=1.0)
    c = 0.4
    shift = 2 * math.sqrt(3) * c * 1.33 * 0.6 / (math.pi * 0.25**2)
    src = np.array([[0.5, -0.5, 12.0]])
    o0, o1 = Optics(**base), Optics(**base, image_plane_um=shift)
    plan = plan_for_sources(o1, (48, 48), src, warn=False)
    dn = torch.zeros(2, 48, 48, dtype=torch.float64)
    a = MultiSliceModel(o0, plan, device="cpu", dtype=torch.float64, aberrations={"defocus": c})(dn, torch.tensor(src))
    b = MultiSliceModel(o1, plan, device="cpu", dtype=torch.float64)(dn, torch.tensor(src))
    wrong = MultiSliceModel(o0, plan, device="cpu", dtype=torch.float64, aberrations={"defocus": -c})(dn, torch.tensor(src))
    err = float((a - b).norm() / b.norm())
    assert err < 0.03, err
    assert float((wrong - b).norm() / b.norm()) > 5 * err


def test_simulate_writes_the_camera_model(tmp_path) -> None:
    out = tmp_path / "acq"
    cmd = [sys.executable, "-m", "napari_fdt", "simulate", "beads", str(out), "--shape", "24", "24", "--n-slices", "2",
           "--sources", "1", "--depth-um", "10", "--no-noise", "--pixel-integration", "auto", "--pupil-edge", "0",
           "--aberrations", "spherical=0.5"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    meta = json.loads((out / "acquisition.json").read_text())
    assert meta["pixel_integration"] is True and meta["pupil_edge"] == 0.0
    truth = json.loads((out / "ground_truth_sources_um.json").read_text())
    assert truth["settings"]["aberrations"] == {"spherical": 0.5}


def test_pupil_and_aberration_gradients_match_finite_differences() -> None:
    """d(loss)/d(NA, edge, Zernike) through the exact homogeneous field and pixel integration (calibration).

    Rotationally symmetric modes: with coma or astigmatism the harmonics' Bessel tables are constants and d/dNA is
    approximate (documented)."""
    opt = Optics(wavelength_um=0.6, n_background=1.33, na=0.5, pixel_size_um=0.4, n_slices=2, slice_spacing_um=1.0)
    src = torch.tensor([[0.8, -0.6, 10.0]], dtype=torch.float64)
    plan = plan_for_sources(opt, (24, 24), src.numpy(), warn=False)
    model = MultiSliceModel(opt, plan, device="cpu", dtype=torch.float64, pupil_edge=0.01, pixel_integration=True)
    assert model.exact_free_field
    dn = torch.zeros(2, 24, 24, dtype=torch.float64)
    dn[:, 8:14, 10:16] = 0.02
    target = torch.rand(1, 24, 24, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def loss(na, edge, z):
        return ((model(dn, src, na=na, pupil_edge=edge, zernike=z) - target) ** 2).sum()

    na = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    edge = torch.tensor(0.01, dtype=torch.float64, requires_grad=True)
    z = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.2], dtype=torch.float64)
    loss(na, edge, z).backward()  # rotationally symmetric constant phase: the J₀ path, d/dJ₀ = −J₁
    z.requires_grad_(True)  # a trained phase may turn non-symmetric: the harmonics path
    loss(na.detach(), edge.detach(), z).backward()
    eps = 1e-5
    with torch.no_grad():
        fd_na = (loss(na + eps, edge, z) - loss(na - eps, edge, z)) / (2 * eps)
        fd_edge = (loss(na, edge + eps, z) - loss(na, edge - eps, z)) / (2 * eps)
        dz = torch.zeros(6, dtype=torch.float64)
        dz[5] = eps
        fd_sph = (loss(na, edge, z + dz) - loss(na, edge, z - dz)) / (2 * eps)
    assert float(na.grad) == pytest.approx(float(fd_na), rel=2e-3)
    assert float(edge.grad) == pytest.approx(float(fd_edge), rel=2e-3)
    assert float(z.grad[5]) == pytest.approx(float(fd_sph), rel=2e-3)


def _padded_by_zero_padding_the_centred_spectrum(spec: torch.Tensor) -> torch.Tensor:
    """An independent reference of the fine grid's spectrum: shift to centred, zero-pad symmetrically (the Nyquist row
    and column split in halves to both ends), shift back."""
    h, w = spec.shape[-2:]
    c = torch.fft.fftshift(spec, dim=(-2, -1))  # index 0 is the Nyquist frequency −n/2
    big = spec.new_zeros((*spec.shape[:-2], 2 * h, 2 * w))
    big[..., h // 2 : h // 2 + h, w // 2 : w // 2 + w] = c
    # the Nyquist row/column sits at index h//2 (resp. w//2) of big: split it between −n/2 and +n/2
    ny_r, ny_c = h // 2, w // 2
    big[..., ny_r + h, :] += 0.5 * big[..., ny_r, :]
    big[..., ny_r, :] *= 0.5
    big[..., :, ny_c + w] += 0.5 * big[..., :, ny_c]
    big[..., :, ny_c] *= 0.5
    return torch.fft.ifftshift(big, dim=(-2, -1))


def test_fine_grid_padding_has_its_adjoint_as_gradient() -> None:
    """The zero-padding onto the twice-finer grid is a linear map with a hand-written backward pass (its adjoint, one
    allocation): it passes torch's gradcheck, and equals an independent centred zero-padding away from the dropped
    Nyquist corner. (The fold onto the coarse grid is gradchecked with the pixel mean it is part of, above.)"""
    from napari_fdt.physics.camera import _pad_spectrum

    g = torch.Generator().manual_seed(0)
    spec = torch.randn(2, 6, 8, dtype=torch.complex128, generator=g)
    spec[..., 3, 4] = 0  # the Nyquist corner (both frequencies at Nyquist) is dropped by design
    ref = _padded_by_zero_padding_the_centred_spectrum(spec)
    assert torch.allclose(_pad_spectrum(spec), ref, atol=1e-12)
    x = spec.clone().requires_grad_()
    assert torch.autograd.gradcheck(_pad_spectrum, (x,))
