"""Initial source positions from the images (the paper's per-image 2-D Gaussian fit), against the truth.

Scenes are small (64×64 px of 0.33 µm, 4 slices of 2 µm, NA 0.8) and simulated with the default noise
of :func:`napari_fdt.sim.simulate`. Two geometries:

- ``FOCUS_NEAR``: the camera focused 17 µm below the volume's bottom face (``image_plane_um`` 25), so a
  source 25 µm deep is 8 µm below the focal plane and its disc (radius 6 µm) lies inside the 21 µm image:
  x, y and the depth are identifiable.
- ``FOCUS_TOP``: the camera focused on the volume's top face (``image_plane_um`` 0): a source 25 µm deep
  is 33 µm below the focal plane, its disc (radius 25 µm) fills the image; x, y are still usable, the
  depth is not.

Tolerances carry a margin over what was measured when they were set (measured values in comments).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from napari_fdt import Acquisition, FDTInputError, FDTWarning, Optics, make_scene, simulate, source_grid
from napari_fdt.recon.calibration.source_fit import (
    GaussianFit,
    calibrate_sigma,
    depth_from_sigma,
    fit_gaussians,
    initial_sources,
)

DX = 0.33
SHAPE = (64, 64)
DEPTH = 25.0


def _optics(image_plane_um: float) -> Optics:
    return Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=DX, n_slices=4,
                  slice_spacing_um=2.0, image_plane_um=image_plane_um)


FOCUS_NEAR = 25.0
FOCUS_TOP = 0.0


def _simulate(image_plane_um: float, scene: str | None, sources: np.ndarray, seed: int = 0):
    opt = _optics(image_plane_um)
    dn = np.zeros((opt.n_slices, *SHAPE), np.float32) if scene is None else make_scene(scene, SHAPE, opt)
    return simulate(dn, opt, sources, device="cpu", seed=seed)


@pytest.fixture(scope="module", autouse=True)
def _one_torch_thread():
    """These fits are thousands of tiny tensor operations: one thread is fastest, and on a busy machine
    several threads wait on each other (measured: the file takes 3.5 s with one thread, 29 s with two on a
    loaded 2-core machine). Restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def letters_near():
    return _simulate(FOCUS_NEAR, "letters", source_grid(3, 15.0, DEPTH))


@pytest.fixture(scope="module")
def letters_top():
    return _simulate(FOCUS_TOP, "letters", source_grid(4, 15.0, DEPTH))


def _lateral_errors(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.hypot(estimate[:, 0] - truth[:, 0], estimate[:, 1] - truth[:, 1])


# -- the Gaussian fit ---------------------------------------------------------------------------

def _gaussian_stack(params, shape=(48, 64), dx=DX):
    h, w = shape
    y = (np.arange(h) - h // 2)[:, None] * dx
    x = (np.arange(w) - w // 2)[None, :] * dx
    return np.stack([a * np.exp(-((x - px) ** 2 + (y - py) ** 2) / (2 * s * s)) + b for px, py, s, a, b in params])


def test_fit_recovers_exact_gaussians() -> None:
    """Exact Gaussians (off-centre, with background, one cut by the border, non-square image): 1e-3 relative."""
    params = [(1.3, -2.1, 2.5, 100.0, 5.0), (-4.0, 3.0, 1.0, 7.0, 0.0), (0.2, 0.1, 4.0, 50.0, -3.0),
              (9.5, -6.0, 2.0, 10.0, 1.0)]  # the last one is centred 0.3 µm from the right border
    fit = fit_gaussians(_gaussian_stack(params), DX)
    assert isinstance(fit, GaussianFit) and len(fit) == len(params)
    truth = np.array(params)
    got = np.column_stack([fit.x_um, fit.y_um, fit.sigma_um, fit.amplitude, fit.background])
    scale = np.abs(truth)
    scale[:, 4] = truth[:, 3]  # background relative to the amplitude (it may be 0)
    np.testing.assert_array_less(np.abs(got - truth), 1e-3 * scale + 1e-9)
    assert np.all(fit.residual < 1e-6) and not fit.at_bound.any()


def test_fit_is_batched_and_deterministic() -> None:
    """Each image's fit does not depend on the others in the batch; repeated calls are identical."""
    params = [(1.3, -2.1, 2.5, 100.0, 5.0), (-4.0, 3.0, 1.0, 7.0, 0.0), (0.2, 0.1, 4.0, 50.0, -3.0)]
    rng = np.random.default_rng(1)
    images = _gaussian_stack(params) + rng.normal(0, 1.0, (3, 48, 64))
    a = fit_gaussians(images, DX)
    b = fit_gaussians(images, DX)
    single = fit_gaussians(images[1], DX)
    for name in ("x_um", "y_um", "sigma_um", "amplitude", "background", "residual"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        np.testing.assert_allclose(getattr(single, name)[0], getattr(a, name)[1], rtol=1e-6, atol=1e-9)


def test_fit_survives_discs_larger_than_the_image_and_sources_outside(letters_top) -> None:
    """No NaN: discs filling the image, a source outside the field, a flat image, a single bright pixel."""
    outside = _simulate(FOCUS_NEAR, None, np.array([[9.0, 0.0, DEPTH], [30.0, 30.0, DEPTH]])).acquisition.images
    flat = np.ones((1, *SHAPE))
    spike = np.zeros((1, *SHAPE))
    spike[0, 10, 40] = 1.0
    images = np.concatenate([letters_top.acquisition.images[:4], outside, flat, spike])
    fit = fit_gaussians(images, DX)
    for name in ("x_um", "y_um", "sigma_um", "amplitude", "background", "residual"):
        assert np.all(np.isfinite(getattr(fit, name))), name
    assert abs(fit.x_um[4] - 9.0) < 0.6  # disc centred 1.5 µm inside the border: still found (measured 0.36)
    assert fit.at_bound[6] and fit.at_bound[7]  # flat: σ at its upper bound; spike: σ at its lower bound
    assert fit.residual[5] > 0.5  # nothing but the faint edge of a disc outside the field (measured 0.82)


# -- positions from the images ----------------------------------------------------------------

def test_initial_sources_lateral_and_depth_when_disc_fits(letters_near) -> None:
    """Letters scene, noise, 3×3 sources over 15 µm, disc inside the image: x, y and depth from the images."""
    truth = letters_near.sources_um
    with warnings.catch_warnings():
        warnings.simplefilter("error", FDTWarning)  # everything identifiable: no warning
        est, report = initial_sources(letters_near.acquisition)
    err = _lateral_errors(est, truth)
    assert np.sqrt(np.mean(err**2)) < 0.3  # measured RMS 0.115 µm
    assert err.max() < 0.5  # measured 0.17 µm
    assert report["depth_source"] == "sigma" and report["depth_identifiable"].all()
    height = truth[:, 2] + letters_near.acquisition.optics.thickness_um - FOCUS_NEAR  # 8 µm below the focus
    assert np.all(np.abs(est[:, 2] - truth[:, 2]) < 0.05 * truth[:, 2])  # measured ≤ 1.2 % (RMS 0.8 %)
    assert np.all(np.abs(est[:, 2] - truth[:, 2]) < 0.10 * height)  # measured ≤ 3.6 % of the height
    assert report["residual"].shape == (9,) and np.all(report["residual"] < 0.6)
    assert report["calibration"]["identifiable"]


def test_initial_sources_lateral_when_disc_fills_the_image(letters_top) -> None:
    """Camera on the top face, sources 25 µm deep (disc of 25 µm radius in a 21 µm image), depth given."""
    truth = letters_top.sources_um
    with warnings.catch_warnings():
        warnings.simplefilter("error", FDTWarning)
        est, report = initial_sources(letters_top.acquisition, depth_um=DEPTH)
    err = _lateral_errors(est, truth)
    assert np.sqrt(np.mean(err**2)) < 1.0  # measured RMS 0.62 µm (3×3 grid: 0.73 µm)
    assert err.max() < 2.2  # measured 1.6 µm (corner sources)
    np.testing.assert_array_equal(est[:, 2], DEPTH)
    assert report["depth_source"] == "depth_um" and report["calibration"] is None
    assert report["filled"].all()


@pytest.mark.parametrize(
    "image_plane_um, shape, depths",
    [(FOCUS_NEAR, (64, 64), [19.0, 21.0, 23.5, 26.0, 27.5]),  # heights 2-10.5 µm below the focus
     (FOCUS_TOP, (96, 96), [1.0, 3.0, 5.0, 7.0])],  # heights 9-15 µm (camera on the top face)
)
def test_depth_from_sigma_recovers_homogeneous_depths(image_plane_um, shape, depths) -> None:
    """Homogeneous medium, noise, source off-centre, depths between the calibration's reference depths."""
    opt = _optics(image_plane_um)
    src = np.array([[1.5, -2.0, d] for d in depths])
    sim = simulate(np.zeros((opt.n_slices, *shape), np.float32), opt, src, device="cpu")
    fit = fit_gaussians(sim.acquisition.images, DX)
    with warnings.catch_warnings():
        warnings.simplefilter("error", FDTWarning)
        est, cal = depth_from_sigma(fit.sigma_um, opt, shape)
    depths = np.asarray(depths)
    height = depths + opt.thickness_um - image_plane_um
    assert cal["identifiable_sources"].all()
    assert np.all(np.abs(est - depths) < 0.10 * depths)  # measured ≤ 0.8 % (near) and ≤ 4.1 % (top)
    assert np.all(np.abs(est - depths) < 0.05 * height)  # measured ≤ 2.2 % and ≤ 1.9 % of the height
    # The calibration is monotone and reported.
    assert np.all(np.diff(cal["sigma_um"]) > 0) and np.all(np.diff(cal["reference_depth_um"]) > 0)
    assert {"slope", "intercept_um", "max_relative_deviation"} <= set(cal["linear"])


# -- errors and warnings ----------------------------------------------------------------------

def test_blank_images_raise() -> None:
    opt = _optics(FOCUS_NEAR)
    with pytest.raises(FDTInputError, match="blank"):
        initial_sources(Acquisition(images=np.zeros((3, *SHAPE), np.float32), optics=opt))
    images = np.ones((3, *SHAPE))
    images[1] = 0.0
    with pytest.raises(FDTInputError, match=r"images: 1 of 3 images are blank.*image 1"):
        fit_gaussians(images, DX)
    with pytest.raises(FDTInputError, match="pixel_size_um"):
        fit_gaussians(np.ones((1, *SHAPE)), 0.0)


def test_invalid_depth_guess_raises(letters_near) -> None:
    for bad in (0.0, -3.0, float("nan"), "25"):
        with pytest.raises(FDTInputError, match="depth_um"):
            initial_sources(letters_near.acquisition, depth_um=bad)


def test_disc_filling_the_image_warns(letters_top) -> None:
    """The depth of a source whose disc fills the image is not identifiable: warn, say what to do."""
    with pytest.warns(FDTWarning, match=r"not identifiable.*depth_um"):
        est, report = initial_sources(letters_top.acquisition)
    assert not report["depth_identifiable"].any()
    assert np.all(np.isfinite(est)) and np.all(est[:, 2] > 0)
    # depth_from_sigma alone: σ far beyond the calibrated range.
    opt = _optics(FOCUS_NEAR)
    cal = calibrate_sigma(opt, SHAPE)
    with pytest.warns(FDTWarning, match="not identifiable"):
        depth, info = depth_from_sigma(np.array([2.0, 3.0 * cal["sigma_max_um"]]), opt, SHAPE)
    assert info["identifiable_sources"].tolist() == [True, False]
    assert depth[1] == pytest.approx(cal["depth_max_um"])  # the lower bound: the disc fills the image
