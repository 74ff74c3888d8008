"""Partial coherence: the emission spectrum, the spectral sum of images and the paper's masks.

Physics checks: the quadrature's moments are exact; fringes from a small bead wash out with the
emission bandwidth as the Gaussian spectrum's coherence factor exp(−(2π·n_b·ΔL·σ/λ²)²/2) predicts for
the geometric path difference ΔL between scattered and direct light; the spectral sum converges in the
number of wavelengths; the mask of a source in a homogeneous medium is the disc of its light cone.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from napari_fdt.errors import FDTInputError
from napari_fdt.model.coherence import (
    FWHM_PER_SIGMA,
    coherence_length_um,
    coherence_masks,
    emission_spectrum,
    spectral_images,
)
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.render import render_images
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.optics import Optics
from napari_fdt.sim.simulate import simulate

LAM = 0.635
N_B = 1.33


def _model(shape, sources, **kw) -> MultiSliceModel:
    base = dict(wavelength_um=LAM, n_background=N_B, na=0.8, pixel_size_um=0.33, n_slices=4, slice_spacing_um=2.0)
    base.update(kw)
    optics = Optics(**base)
    return MultiSliceModel(optics, plan_for_sources(optics, shape, np.asarray(sources)), device="cpu")


def _radius_grid(shape, dx):
    h, w = shape
    y = (np.arange(h) - h // 2)[:, None] * dx
    x = (np.arange(w) - w // 2)[None, :] * dx
    return np.broadcast_to(y, shape), np.broadcast_to(x, shape)


# -- the spectrum ------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [2, 3, 5, 9, 15])
@pytest.mark.parametrize("fwhm", [0.02, 0.06])
def test_emission_spectrum_moments_are_exact(n: int, fwhm: float) -> None:
    lam, w = emission_spectrum(LAM, fwhm, n)
    sigma = fwhm / FWHM_PER_SIGMA
    assert lam.shape == w.shape == (n,)
    assert np.all(w > 0) and np.all(lam > 0)
    assert abs(w.sum() - 1.0) < 1e-12
    mean = float(np.sum(w * lam))
    assert abs(mean - LAM) < 1e-12
    assert abs(float(np.sum(w * (lam - mean) ** 2)) - sigma**2) < 1e-12
    if n >= 3:  # degree 4 <= 2n - 1: the Gaussian's fourth moment 3σ⁴ is exact too
        assert abs(float(np.sum(w * (lam - mean) ** 4)) - 3 * sigma**4) < 1e-15
    assert np.all(np.diff(lam) > 0)


def test_emission_spectrum_single_wavelength_and_fwhm_constant() -> None:
    assert FWHM_PER_SIGMA == pytest.approx(2.3548, abs=1e-4)
    for lam, w in (emission_spectrum(LAM, 0.04, 1), emission_spectrum(LAM, 0.0, 9)):
        assert lam.tolist() == [LAM] and w.tolist() == [1.0]


@pytest.mark.parametrize(
    "args, field",
    [((LAM, -0.01, 5), "bandwidth_um"), ((LAM, math.nan, 5), "bandwidth_um"), ((LAM, 0.04, 0), "n_wavelengths"),
     ((LAM, 0.04, True), "n_wavelengths"), ((LAM, 0.04, 2.5), "n_wavelengths"), ((LAM, 0.4, 9), "bandwidth_um")],
)
def test_emission_spectrum_rejects_bad_input(args, field: str) -> None:
    with pytest.raises(FDTInputError) as exc:
        emission_spectrum(*args)
    assert exc.value.field == field


def test_coherence_length() -> None:
    assert coherence_length_um(LAM, 0.04, N_B) == pytest.approx(LAM**2 / (N_B * 0.04))
    assert 4.0 < coherence_length_um(LAM, 0.06, N_B) < coherence_length_um(LAM, 0.02, N_B) < 16.0
    assert coherence_length_um(LAM, 0.0, N_B) == math.inf


# -- the spectral sum ---------------------------------------------------------------------------
def test_spectral_images_one_wavelength_is_the_model_exactly() -> None:
    src = np.array([[0.0, 0.0, 20.0], [2.0, -1.0, 25.0]])
    model = _model((32, 40), src)
    dn = torch.zeros(4, 32, 40)
    dn[1, 10:20, 12:30] = 0.03
    s = torch.tensor(src, dtype=torch.float32)
    gain = torch.tensor([1.5, 0.7])
    ref = model(dn, s, gain)
    assert torch.equal(spectral_images(model, dn, s, gain, [LAM], [1.0]), ref)
    assert torch.equal(spectral_images(model, dn, s, gain, np.array([LAM]), np.array([1.0])), ref)
    assert torch.equal(spectral_images(model, dn, s, gain), ref)
    # Several wavelengths: the weighted sum of the model at each (its wavelength override).
    lam, w = emission_spectrum(LAM, 0.05, 3)
    manual = sum(float(wk) * model(dn, s, gain, wavelength_um=float(lk)) for lk, wk in zip(lam, w))
    torch.testing.assert_close(spectral_images(model, dn, s, gain, lam, w), manual, rtol=1e-6, atol=0)
    with pytest.raises(FDTInputError):
        spectral_images(model, dn, s, gain, lam, w[:2])


def test_spectral_images_are_differentiable() -> None:
    src = np.array([[0.0, 0.0, 20.0]])
    model = _model((24, 24), src)
    dn = torch.zeros(4, 24, 24, requires_grad=True)
    s = torch.tensor(src, dtype=torch.float32, requires_grad=True)
    lam = torch.tensor([0.60, LAM, 0.67], requires_grad=True)
    w = torch.tensor([0.25, 0.5, 0.25], requires_grad=True)
    spectral_images(model, dn, s, None, lam, w).square().sum().backward()
    for t in (dn, s, lam, w):
        assert t.grad is not None and torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0


# -- fringe visibility --------------------------------------------------------------------------
# A point-like bead (r 0.6 µm, Δn 0.05) in slice 0 straight above the source; the camera focuses 12 µm
# above the volume, so the bead's fringes spread over rs = Δ·tan(asin(NA/n_b)) ≈ 21 µm with path
# differences up to 0.7 coherence lengths at 60 nm. NA 1.0 makes them large for a cheap window.
FRINGE = dict(na=1.0, pixel_size_um=0.3, image_plane_um=-12.0)
FRINGE_SHAPE = (128, 128)
FRINGE_DEPTH = 20.0


@pytest.fixture(scope="module")
def fringe_images():
    src = np.array([[0.0, 0.0, FRINGE_DEPTH]])
    model = _model(FRINGE_SHAPE, src, **FRINGE)
    y, x = _radius_grid(FRINGE_SHAPE, 0.3)
    r = np.hypot(x, y)
    bead = torch.zeros(4, *FRINGE_SHAPE)
    bead[0] = torch.from_numpy((r < 0.6).astype(np.float32) * 0.05)
    s = torch.tensor(src, dtype=torch.float32)
    out = {}
    with torch.no_grad():
        for fwhm, k in [(0.0, 1), (0.02, 9), (0.06, 9), (0.06, 15)]:
            lam, w = emission_spectrum(LAM, fwhm, k)
            img = spectral_images(model, bead, s, None, lam, w)[0].double().numpy()
            ref = spectral_images(model, torch.zeros_like(bead), s, None, lam, w)[0].double().numpy()
            out[(fwhm, k)] = (img, ref)
    return model, r, out


def _fringe_geometry(model):
    o = model.optics
    h = FRINGE_DEPTH + o.thickness_um - o.image_plane_um  # source → focal plane
    z_bead = FRINGE_DEPTH + 0.5 * o.slice_spacing_um  # source → bead (slice 0's screen)
    delta = h - z_bead  # bead → focal plane
    rs = min(delta * math.tan(math.asin(o.na / o.n_background)), FRINGE_SHAPE[0] * 0.3 / 2 / 0.9)
    return h, z_bead, delta, rs


def _visibility(img, ref, ring):
    return float(np.sqrt(np.mean(((img - ref) / ref)[ring] ** 2)))


def test_fringe_visibility_falls_with_bandwidth(fringe_images) -> None:
    model, r, out = fringe_images
    h, z_bead, delta, rs = _fringe_geometry(model)
    ring = (r >= 0.5 * rs) & (r < 0.9 * rs)
    v = {key: _visibility(*out[key], ring) for key in out}
    # Measured: 0.0183, 0.0175, 0.0086.
    assert v[(0.0, 1)] > v[(0.02, 9)] > v[(0.06, 9)]
    assert v[(0.06, 9)] < 0.6 * v[(0.0, 1)]
    # The coherence factor of a Gaussian spectrum at the geometric path difference, pixel by pixel.
    d_l = z_bead + np.hypot(delta, r) - np.hypot(h, r)
    d0 = (out[(0.0, 1)][0] - out[(0.0, 1)][1]) / out[(0.0, 1)][1]
    for fwhm in (0.02, 0.06):
        a = 2 * math.pi * N_B * d_l * (fwhm / FWHM_PER_SIGMA) / LAM**2
        predicted = math.sqrt(np.sum((np.exp(-(a**2) / 2) * d0)[ring] ** 2) / np.sum(d0[ring] ** 2))
        measured = v[(fwhm, 9)] / v[(0.0, 1)]
        assert measured == pytest.approx(predicted, abs=0.08)  # measured 0.952 vs 0.890, 0.471 vs 0.438


def test_spectral_sum_converges_in_the_number_of_wavelengths(fringe_images) -> None:
    model, r, out = fringe_images
    rs = _fringe_geometry(model)[3]
    ring = (r >= 0.5 * rs) & (r < 0.9 * rs)
    a, b = out[(0.06, 9)][0], out[(0.06, 15)][0]
    assert np.linalg.norm(a - b) / np.linalg.norm(b) < 0.01  # measured 0.0036
    va, vb = _visibility(*out[(0.06, 9)], ring), _visibility(*out[(0.06, 15)], ring)
    assert va == pytest.approx(vb, rel=0.05)  # measured 0.0086 vs 0.0084


# -- masks --------------------------------------------------------------------------------------
MASK_SHAPE = (128, 128)
MASK_SOURCES = np.array([[0.0, 0.0, 20.0], [3.0, -2.0, 20.0]])


@pytest.fixture(scope="module")
def mask_model() -> MultiSliceModel:
    return _model(MASK_SHAPE, MASK_SOURCES, na=0.5)


def test_mask_is_the_disc_of_the_light_cone(mask_model) -> None:
    o = mask_model.optics
    masks = coherence_masks(mask_model, MASK_SOURCES).cpu().numpy()
    assert masks.shape == (2, *MASK_SHAPE) and masks.dtype == np.float32
    assert set(np.unique(masks)) == {0.0, 1.0}
    h = 20.0 + o.thickness_um - o.image_plane_um
    r_geo = h * math.tan(math.asin(o.na / o.n_background))  # 11.36 µm, fits in the 42 µm image
    y, x = _radius_grid(MASK_SHAPE, o.pixel_size_um)
    for m, (xs, ys, _) in zip(masks, MASK_SOURCES):
        area = m.sum() * o.pixel_size_um**2
        r_eq = math.sqrt(area / math.pi)
        # The 50 % contour lies inside the geometric edge, where the Fresnel edge falls off
        # (intensity 1/4 of the disc's level at the geometric edge). Measured: 0.904.
        assert 0.85 < r_eq / r_geo < 0.95
        disc = np.hypot(x - xs, y - ys) <= r_eq
        iou = np.sum(disc & (m > 0)) / np.sum(disc | (m > 0))
        assert iou > 0.97  # one round disc (measured 0.999)
        assert (m * x).sum() / m.sum() == pytest.approx(xs, abs=0.05)
        assert (m * y).sum() / m.sum() == pytest.approx(ys, abs=0.05)


def test_mask_with_spectrum_and_literal_rule(mask_model) -> None:
    lam, w = emission_spectrum(LAM, 0.04, 5)
    plain = coherence_masks(mask_model, MASK_SOURCES)
    spectral = coherence_masks(mask_model, MASK_SOURCES, wavelengths_um=lam, weights=w)
    assert torch.mean((plain != spectral).float()) < 0.01
    # Without the blur the raw image's axial spike (about twice the disc's level) sets the maximum:
    # half of it cuts through the fringes and leaves broken rings (measured: 44 % of the blurred mask's area).
    raw = coherence_masks(mask_model, MASK_SOURCES[:1], smooth_um=0.0)
    assert set(torch.unique(raw).tolist()) <= {0.0, 1.0}
    assert raw.sum() < 0.5 * plain[0].sum()
    # The threshold is relative to each image's own maximum.
    low = coherence_masks(mask_model, MASK_SOURCES, threshold=0.2)
    assert torch.all(low >= plain) and low.sum() > plain.sum()


def test_masks_carry_no_gradient_and_check_input(mask_model) -> None:
    s = torch.tensor(MASK_SOURCES, dtype=torch.float32, requires_grad=True)
    assert not coherence_masks(mask_model, s).requires_grad
    with pytest.raises(FDTInputError) as exc:
        coherence_masks(mask_model, s, threshold=1.5)
    assert exc.value.field == "threshold"


def test_masks_are_made_in_batches(mask_model, monkeypatch) -> None:
    """The masks of many sources are imaged ``batch_size`` at a time (their memory is a batch's fields, not the stack's:
    a full-size stack's 1521 masks in one pass took over 24 GB), and each mask is the one made alone."""
    import napari_fdt.model.coherence as coherence

    sources = np.array([[x, y, 20.0] for x in (-3.0, 0.0, 3.0) for y in (-2.0, 2.0)] + [[1.0, 1.0, 22.0]])
    alone = torch.stack([coherence_masks(mask_model, sources[i:i + 1])[0] for i in range(len(sources))])
    seen: list[int] = []
    real = coherence.spectral_images

    def spy(model, dn, src, *a, **k):
        seen.append(int(src.shape[0]))
        return real(model, dn, src, *a, **k)

    monkeypatch.setattr(coherence, "spectral_images", spy)
    batched = coherence_masks(mask_model, sources, batch_size=3)
    assert seen == [3, 3, 1]
    assert torch.equal(batched, alone)
    seen.clear()
    coherence_masks(mask_model, sources)
    assert seen == [len(sources)]  # (fewer than MASK_BATCH: one pass)
    assert coherence.MASK_BATCH <= 16


# -- simulation ---------------------------------------------------------------------------------
def test_simulate_renders_the_spectral_sum() -> None:
    optics = Optics(wavelength_um=LAM, n_background=N_B, na=0.8, pixel_size_um=0.33, n_slices=2, slice_spacing_um=2.0)
    src = np.array([[0.0, 0.0, 15.0], [3.0, 1.0, 15.0]])
    dn = np.zeros((2, 24, 24), np.float32)
    dn[0, 8:16, 8:16] = 0.05
    sim = simulate(dn, optics, src, noise=False, bandwidth_um=0.04, n_wavelengths=5, device="cpu", batch_size=1)
    s = sim.settings
    assert s["bandwidth_um"] == 0.04 and s["n_wavelengths"] == 5 and len(s["emission_wavelengths_um"]) == 5
    assert s["coherence_length_um"] == pytest.approx(coherence_length_um(LAM, 0.04, N_B))
    lam, w = emission_spectrum(LAM, 0.04, 5)
    model = MultiSliceModel(optics, sim.plan, device="cpu")
    clean = render_images(model, dn, src, wavelengths_um=lam, weights=w)
    expected = clean * (sim.scale * sim.brightness)[:, None, None]
    np.testing.assert_allclose(sim.acquisition.images, expected, rtol=1e-5, atol=1e-3 * expected.max())
    coherent = simulate(dn, optics, src, noise=False, device="cpu")
    assert coherent.settings["bandwidth_um"] == 0.0 and coherent.settings["emission_wavelengths_um"] == [LAM]
    assert coherent.settings["coherence_length_um"] is None
    assert not np.allclose(coherent.acquisition.images, sim.acquisition.images, rtol=1e-3)
