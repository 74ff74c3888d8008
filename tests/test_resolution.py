"""The half-set resolution (issue 25): Fourier shell correlation against statistics with a known answer, the halves'
split, the settings the halves run with, and the figure in RI.json from ``fdt reconstruct --half-set-resolution``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from napari_fdt.recon.assess.fsc import HALF_SET_THRESHOLD, fsc_curves, resolution, resolutions, truth_fsc_from_halves
from napari_fdt.recon.assess.validation import split_halves

PIXEL_UM, SLICE_UM = 0.25, 1.0


def _band_limited(shape, k_max_per_um: float, rng) -> np.ndarray:
    """White noise with every lateral frequency above ``k_max_per_um`` removed (all axial frequencies kept)."""
    f = np.fft.fftn(rng.standard_normal(shape))
    ky = np.fft.fftfreq(shape[1], PIXEL_UM)[:, None]
    kx = np.fft.fftfreq(shape[2], PIXEL_UM)[None, :]
    f[:, np.sqrt(kx**2 + ky**2) > k_max_per_um] = 0
    return np.fft.ifftn(f).real


def test_fsc_of_a_volume_with_itself_is_one_and_with_independent_noise_near_zero() -> None:
    rng = np.random.default_rng(0)
    a = rng.standard_normal((8, 64, 64))
    same = fsc_curves(a, a, PIXEL_UM, SLICE_UM)
    for d, c in same.items():
        np.testing.assert_allclose(c.correlation, 1.0, atol=1e-12, err_msg=d)
    other = fsc_curves(a, rng.standard_normal(a.shape), PIXEL_UM, SLICE_UM)
    lat = other["lateral"]
    # a bin of n independent complex Fourier voxels correlates by chance with a standard deviation of about 1/sqrt(n)
    big = lat.n_voxels[1:] > 50
    assert np.all(np.abs(lat.correlation[1:][big]) < 4.0 / np.sqrt(lat.n_voxels[1:][big]))
    assert lat.grid_limit_um == pytest.approx(2 * PIXEL_UM) and other["axial"].grid_limit_um == pytest.approx(2 * SLICE_UM)
    assert lat.frequency_per_um[-1] == pytest.approx(0.5 / PIXEL_UM)
    assert other["axial"].frequency_per_um[-1] == pytest.approx(0.5 / SLICE_UM)


def test_half_sets_find_the_band_limit_of_a_signal_in_noise() -> None:
    """Two halves = one band-limited signal + independent noise: they correlate at about S/(S+N) inside the band and not
    outside, so the 1/7 crossing is the band's edge; the full volume's FSC with the truth is sqrt(2F/(1+F))."""
    rng = np.random.default_rng(1)
    shape, k_max = (8, 96, 96), 1.0  # cycles/µm: a 1 µm period, Nyquist is 2 cycles/µm
    signal = _band_limited(shape, k_max, rng)
    signal *= 1.0 / signal.std()
    noise = 0.5  # the band is π/16 of the lateral spectrum: S/N per Fourier voxel inside it about 5.1/0.25, FSC about 0.95
    a = signal + noise * rng.standard_normal(shape)
    b = signal + noise * rng.standard_normal(shape)
    lateral = fsc_curves(a, b, PIXEL_UM, SLICE_UM)["lateral"]
    found = resolution(lateral, HALF_SET_THRESHOLD)
    bin_um = lateral.frequency_per_um[1]
    assert found.resolution_um is not None
    # the edge taper spreads the band's edge over a few rings (the lateral sides' eighth: 12 px here, about 3 rings)
    assert k_max - bin_um <= 1.0 / found.resolution_um <= k_max + 3 * bin_um
    # the halves' prediction of the full volume's correlation with the truth, inside the band
    full = fsc_curves((a + b) / 2, signal, PIXEL_UM, SLICE_UM)["lateral"]
    inside = (lateral.frequency_per_um > 0.1) & (lateral.frequency_per_um < 0.8 * k_max)
    np.testing.assert_allclose(truth_fsc_from_halves(lateral.correlation[inside]), full.correlation[inside], atol=0.03)


def test_a_curve_above_the_threshold_everywhere_is_resolved_to_the_grid() -> None:
    rng = np.random.default_rng(2)
    a = rng.standard_normal((4, 32, 32))
    found = resolutions(a, a + 0.01 * rng.standard_normal(a.shape), PIXEL_UM, SLICE_UM, HALF_SET_THRESHOLD)
    assert found["lateral"].resolution_um is None and found["lateral"].bound_um == pytest.approx(2 * PIXEL_UM)
    assert "the grid" in found["axial"].describe()


def test_halves_split_every_pair_of_neighbours_and_cover_the_field() -> None:
    from napari_fdt import source_grid

    src = source_grid(7, 5.0, 20.0)  # 49 sources 5 µm apart
    a, b = split_halves(src, seed=3)
    assert len(a) == 25 and len(b) == 24
    assert sorted(np.concatenate([a, b]).tolist()) == list(range(len(src)))
    for mine, other in ((a, b), (b, a)):  # every source has a source of the other half within one grid step and a half
        d = np.hypot(*(src[mine, None, :2] - src[None, other, :2]).transpose(2, 0, 1)).min(axis=1)
        assert d.max() <= 1.5 * 5.0 * np.sqrt(2)
    assert np.array_equal(split_halves(src, seed=3)[0], a)  # the seed decides


def test_the_halves_settings_fix_what_the_run_chose(scene16) -> None:
    from napari_fdt.recon.loop.model_parts import switch
    from napari_fdt.recon.run.half_sets import chosen_settings
    from napari_fdt.recon.run.solver import Reconstructor
    from napari_fdt.recon.settings.config import SolverConfig

    rec = Reconstructor(scene16.acquisition, SolverConfig(half_set_resolution=True), device="cpu")
    rec.loss_weights = dataclasses.replace(rec.loss_weights, tv_xy=3.0, tv_z=1.5)
    rec.parts = {**rec.parts, "pupil": True, "aberrations": False}
    fixed = chosen_settings(rec)
    assert (fixed.tv_xy_weight, fixed.tv_z_weight) == (3.0, 1.5)
    assert switch(fixed.calibrate_pupil) is True and switch(fixed.calibrate_aberrations) is False
    assert fixed.half_set_resolution is False and fixed.parts_pilot is False
    assert fixed.stages == rec.requested_config.stages and fixed.seed == rec.requested_config.seed


def test_the_halves_run_with_the_run_s_choices_and_report_a_resolution(tmp_path: Path, capsys) -> None:
    """``fdt reconstruct --half-set-resolution``: the result written first, then RI.json again with a ``resolution``
    section whose figures lie between the grid's Nyquist period and the field of view; the truth's own figure beside it."""
    from benchmarks.scenes import tiny_scene
    from napari_fdt import write_acquisition, write_volume_tiff
    from napari_fdt.cli import main

    sim = tiny_scene(grid=4, seed=2)
    folder = write_acquisition(sim.acquisition, tmp_path / "acq")
    o = sim.acquisition.optics
    truth = tmp_path / "truth.tif"
    write_volume_tiff(truth, sim.ri, (o.slice_spacing_um, o.pixel_size_um, o.pixel_size_um))
    settings = tmp_path / "settings.json"
    settings.write_text(json.dumps({"stages": [{"factor": 2, "iterations": 6}, {"factor": 1, "iterations": 8}],
                                    "final_stage_min_passes": 0, "batch_size": 4}))
    out = tmp_path / "ri.tif"
    assert main(["reconstruct", str(folder), "--out", str(out), "--config", str(settings), "--device", "cpu", "--quiet",
                 "--half-set-resolution", "--tv-xy-weight", "auto", "--truth", str(truth)]) == 0
    said = capsys.readouterr()
    report = json.loads(out.with_suffix(".json").read_text())
    res = report["resolution"]
    assert res["n_images"] == [8, 8]
    assert "resolution (half-set FSC" in said.out
    from napari_fdt.physics.band import band_limit_per_um

    band = band_limit_per_um(o, sim.acquisition.image_shape, sim.acquisition.sources_um)
    for d, cell in (("lateral", o.pixel_size_um), ("axial", o.slice_spacing_um)):
        r = res["directions"][d]
        assert r["grid_limit_um"] == pytest.approx(2 * cell)
        assert r["band_limit_um"] == pytest.approx(1.0 / band[d])
        # the figure: never finer than the grid nor the band, and the coarsest of what sets it
        assert res[f"{d}_um"] == r["resolution_um"] >= max(2 * cell, r["band_limit_um"]) - 1e-9
        assert r["limited_by"] in ("grid", "band", "halves") and res[f"{d}_um"] <= 32 * cell
        assert len(r["fsc"]["correlation"]) == len(r["fsc"]["frequency_per_um"])
        assert report["metrics"]["resolution_against_truth"][d]["grid_limit_um"] == pytest.approx(2 * cell)
    # the halves ran with the weight the run chose (no trials of their own): the report names it
    assert report["regularisation"]["chosen"] is not None
    assert report["config"]["half_set_resolution"] is True


def test_the_plan_prices_the_halves(scene16) -> None:
    """Asked for, the plan says what the halves add: each half's stages, on its half of the sources, about as long as
    the run's stages (the halves' batches are the run's); not asked for, nothing."""
    from napari_fdt.recon.loop.plan import plan_for
    from napari_fdt.recon.settings.config import SolverConfig

    plain, _ = plan_for(scene16.acquisition, SolverConfig(), "cpu")
    asked, _ = plan_for(scene16.acquisition, SolverConfig(half_set_resolution=True), "cpu")
    assert plain.half_sets_s is None and "half-set" not in plain.summary()
    stages = sum(p.iterations_s for p in asked.phases if not p.trials)  # every stage once (and the pilot), not the parts' tests
    assert 1.0 * stages <= asked.half_sets_s <= 2.5 * stages
    assert "then the half-set resolution" in asked.summary()
    assert asked.to_dict()["predicted_extra_s_half_set_resolution"] == asked.half_sets_s


def test_the_band_limit_of_sources_far_below_is_the_pupil_and_its_depth_of_field() -> None:
    from napari_fdt import Optics
    from napari_fdt.physics.band import band_limit_per_um, illumination_angle_rad

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.5, pixel_size_um=0.5, n_slices=8, slice_spacing_um=2.0)
    far = np.array([[0.0, 0.0, 1e7]])
    band = band_limit_per_um(o, (64, 64), far)
    assert illumination_angle_rad(o, (64, 64), far) < 1e-5
    assert band["lateral"] == pytest.approx(o.na / o.wavelength_um, rel=1e-5)
    assert 1.0 / band["axial"] == pytest.approx(o.depth_of_field_um, rel=1e-9)
    # a source on the axis 16·√2 µm below a field of 32 µm: the ray to a corner (16·√2 µm off the axis) is at 45°
    near = np.array([[0.0, 0.0, 16.0 * np.sqrt(2.0)]])
    assert illumination_angle_rad(o, (64, 64), near) == pytest.approx(np.pi / 4)
    assert band_limit_per_um(o, (64, 64), near)["lateral"] == pytest.approx((0.5 + 1.33 * np.sqrt(0.5)) / 0.635)


def _normalised_images(delta_n: np.ndarray, optics, sources_um: np.ndarray) -> np.ndarray:
    from napari_fdt import simulate

    sim = simulate(delta_n.astype(np.float32), optics, sources_um, noise=False, jitter_xy_um=0.0, jitter_depth_um=0.0,
                   brightness_spread=0.0, device="cpu")
    im = sim.acquisition.images.astype(np.float64)
    return im / im.mean()


@pytest.mark.filterwarnings("ignore")
def test_a_grating_beyond_the_band_leaves_no_trace_in_the_images_and_one_inside_does() -> None:
    """The forward model against the band limit: a weak lateral grating (Δn 1e-3 in one 1 µm slice) changes the images
    by about 1 % inside the band and by two orders less beyond it, for a source far below the axis (band 1.35
    cycles/µm); a source 30 µm to the side and 60 µm below tilts the light enough to carry 1.8 cycles/µm."""
    from napari_fdt import Optics
    from napari_fdt.physics.band import band_limit_per_um

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.2, n_slices=2, slice_spacing_um=1.0)
    x = (np.arange(64) - 32) * o.pixel_size_um

    def change(k_per_um: float, src: np.ndarray) -> float:
        dn = np.zeros((2, 64, 64))
        dn[0] = 1e-3 * np.cos(2 * np.pi * k_per_um * x)[None, :]
        diff = _normalised_images(dn, o, src) - _normalised_images(np.zeros_like(dn), o, src)
        return float(diff[0, 16:48, 16:48].std())  # the field's centre: the periodic grid's edges aside

    grid_k = [m / (64 * o.pixel_size_um) for m in (10, 19, 23)]  # 0.78, 1.48, 1.80 cycles/µm, periodic on the grid
    below = np.array([[0.0, 0.0, 200.0]])
    band = band_limit_per_um(o, (64, 64), below)["lateral"]
    assert grid_k[0] < band < grid_k[1]
    inside, beyond, far_beyond = (change(k, below) for k in grid_k)
    assert inside > 5e-3 and beyond < 0.05 * inside and far_beyond < 0.05 * inside
    side = np.array([[-30.0, 0.0, 60.0]])
    assert band_limit_per_um(o, (64, 64), side)["lateral"] > grid_k[2]
    assert change(grid_k[2], side) > 0.3 * change(grid_k[0], side)


def test_too_few_images_for_two_halves_are_refused_before_the_run(tmp_path: Path, capsys) -> None:
    from benchmarks.scenes import tiny_scene
    from napari_fdt import write_acquisition
    from napari_fdt.cli import main

    folder = write_acquisition(tiny_scene(grid=2, seed=1).acquisition, tmp_path / "four")  # 4 images
    out = tmp_path / "ri.tif"
    assert main(["reconstruct", str(folder), "--out", str(out), "--device", "cpu", "--half-set-resolution"]) == 2
    said = capsys.readouterr().err
    assert "half_set_resolution" in said and "at least 8 images" in said and not out.exists()
