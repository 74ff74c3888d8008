"""Planning-time checks of the sampling (``napari_fdt.physics.grid.plan_grid``, ``docs/physics.md`` §4 and §7).

Each warning is checked twice: that it fires (naming its field and the fix) where it should and stays silent on
the shipped geometries, and that the problem it names is real, by measuring the image error it predicts against
a better-sampled reference (a wider window, or a finer grid) with the forward model in float64.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import napari_fdt.physics.grid as grid
from napari_fdt.errors import FDTWarning
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.physics.grid import next_fast_even, plan_for_sources
from napari_fdt.physics.optics import Optics
from napari_fdt.sim.simulate import source_grid

ROOT = Path(__file__).resolve().parents[1]

#: The hard-case base geometry (benchmarks/hard_cases.py): λ 0.6 µm, n_b 1.33, NA 0.5, 8 slices of 1 µm.
BASE = dict(wavelength_um=0.6, n_background=1.33, na=0.5, pixel_size_um=0.5, n_slices=8, slice_spacing_um=1.0)
SOURCES = np.array([[0.0, 0.0, 20.0], [3.0, 3.0, 20.0], [-3.0, 3.0, 20.0]])


def _optics(**kw) -> Optics:
    return Optics(**{**BASE, **kw})


def _bead(optics: Optics, shape: tuple[int, int], dn: float) -> np.ndarray:
    """A soft bead of contrast ``dn``, radius 3 µm, at the volume's centre."""
    n, (h, w), dx, dz = optics.n_slices, shape, optics.pixel_size_um, optics.slice_spacing_um
    z = (np.arange(n) - (n - 1) / 2) * dz
    y = (np.arange(h) - h // 2) * dx
    x = (np.arange(w) - w // 2) * dx
    r = np.sqrt(z[:, None, None] ** 2 + y[None, :, None] ** 2 + x[None, None, :] ** 2)
    return dn / (1.0 + np.exp((r - 3.0) / 0.3))


def _images(optics, plan, dn, src, padded=None) -> np.ndarray:
    if padded is not None:
        h, w = plan.image_shape
        plan = dataclasses.replace(plan, padded_shape=padded, offset=(padded[0] // 2 - h // 2, padded[1] // 2 - w // 2))
    model = MultiSliceModel(optics, plan, device="cpu", dtype=torch.float64)
    with torch.no_grad():
        return model(torch.as_tensor(dn, dtype=torch.float64), torch.as_tensor(src, dtype=torch.float64)).numpy()


def _rel(a, b) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def _window_error(optics, shape, src, dn, factor=3, **plan_kw):
    """Images on the planned window against a window ``factor`` times wider; returns (error, plan)."""
    plan = plan_for_sources(optics, shape, src, warn=False, **plan_kw)
    wide = tuple(next_fast_even(factor * s) for s in plan.padded_shape)
    return _rel(_images(optics, plan, dn, src), _images(optics, plan, dn, src, padded=wide)), plan


# -- the window holds the pupil's diffraction tails --------------------------------------------------------


@pytest.mark.parametrize("case", ["hard_baseline", "na_0.3_shallow", "focal_plane_inside"])
def test_planned_window_holds_the_pupil_tails(case, monkeypatch) -> None:
    """Homogeneous medium (exact answer: no wrap-around): the planned window is within 0.3 % of a 3× wider one.

    Without the pupil-tail term (PUPIL_TAIL_UNITS = 0, the former rule) the same geometries lose 1.5–2.6 %:
    the periodic copies' defocused discs ended less than λ/(2·pupil_taper·NA) ≈ 20–33 µm beyond the image.
    """
    optics, src = {
        "hard_baseline": (_optics(), SOURCES),
        "na_0.3_shallow": (_optics(na=0.3), SOURCES * [1, 1, 0.25]),  # sources 5 µm deep
        "focal_plane_inside": (_optics(image_plane_um=4.0), SOURCES),
    }[case]
    shape = (32, 32)
    dn = np.zeros((optics.n_slices, *shape))
    err, plan = _window_error(optics, shape, src, dn)
    assert err < 3e-3, (plan.padded_shape, err)
    monkeypatch.setattr(grid, "PUPIL_TAIL_UNITS", 0.0)
    old_err, old_plan = _window_error(optics, shape, src, dn)
    assert old_plan.padded_shape[0] < plan.padded_shape[0] and old_err > 1e-2, (old_plan.padded_shape, old_err)


def test_deep_sources_need_no_warning() -> None:
    """Sources 300 µm deep on the hard-case geometry: a 384² window, silent, and it holds their light.

    Measured (float64, Δn 0.02 bead): 2.2e-3 against a 2× wider window (1.2e-3 on the homogeneous medium; the
    float32 error at this depth is 2.2e-5, docs/hard_cases.md): below shot noise, nothing to warn about.
    """
    optics = _optics()
    src = np.array([[1.5, 1.5, 300.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error", FDTWarning)
        plan = plan_for_sources(optics, (32, 32), src)
    assert plan.padded_shape == (384, 384)
    err, _ = _window_error(optics, (32, 32), src, _bead(optics, (32, 32), 0.02), factor=2)
    assert err < 5e-3


def test_capped_window_warns_and_costs_accuracy(monkeypatch) -> None:
    """A window capped below what the pupil's tails need is planned, with a warning naming the cap and the fix."""
    optics, shape = _optics(), (32, 32)
    monkeypatch.setattr(grid, "MAX_PADDED_SIDE", 72)  # the light cone needs 64 px, the pupil's tails 90
    with pytest.warns(FDTWarning, match=r"^sources_um: the window is capped at 72 px") as rec:
        plan = plan_for_sources(optics, shape, SOURCES)
    message = str(rec[0].message)
    assert "crop the images or the source range" in message and plan.padded_shape == (72, 72)
    dn = np.zeros((optics.n_slices, *shape))
    err = _rel(_images(optics, plan, dn, SOURCES), _images(optics, plan, dn, SOURCES, padded=(216, 216)))
    assert err > 5e-3  # what the warning is about


def test_hard_pupil_edge_warns() -> None:
    with pytest.warns(FDTWarning, match=r"^pupil_taper 0: a hard pupil edge") as rec:
        plan_for_sources(_optics(), (32, 32), SOURCES, pupil_taper=0.0)
    assert "use the default 0.03" in str(rec[0].message)


# -- the grid's Nyquist frequency against the sources' band limit --------------------------------------------


def _grid_error(dx: float, dn: float) -> tuple[float, tuple[str, ...]]:
    """Images of a bead on pixels of ``dx`` against the same band-limited bead on pixels of dx/2 (same window)."""
    fov = 16.0
    n = int(round(fov / dx)) // 2 * 2
    coarse, fine = _optics(pixel_size_um=dx), _optics(pixel_size_um=dx / 2)
    plan = plan_for_sources(coarse, (n, n), SOURCES, warn=False)
    fine_plan = plan_for_sources(fine, (2 * n, 2 * n), SOURCES, warn=False)
    padded = (2 * plan.padded_shape[0], 2 * plan.padded_shape[1])  # the same period: only the sampling differs
    dn_fine = _bead(fine, (2 * n, 2 * n), dn)
    f = np.fft.fftfreq(2 * n, dx / 2)
    keep = (np.abs(f)[:, None] < 1 / (2 * dx)) & (np.abs(f)[None, :] < 1 / (2 * dx))
    dn_fine = np.real(np.fft.ifft2(np.fft.fft2(dn_fine) * keep))  # representable on both grids
    a = _images(coarse, plan, dn_fine[:, ::2, ::2], SOURCES)
    b = _images(fine, fine_plan, dn_fine, SOURCES, padded=padded)[:, ::2, ::2]
    return _rel(a, b), plan.warnings


def test_nyquist_inside_the_band_limit_warns_only_where_it_costs() -> None:
    """0.5 µm pixels keep 64 % of the roll-off: below 1 % error, silent. 0.55 µm keep 23 %: over 1 %, a warning."""
    err_ok, warned_ok = _grid_error(0.5, 0.05)
    assert err_ok < 1e-2 and not warned_ok, (err_ok, warned_ok)
    err_bad, warned_bad = _grid_error(0.55, 0.05)
    assert err_bad > 1e-2, err_bad
    assert len(warned_bad) == 1 and warned_bad[0].startswith("pixel_size_um 0.55: the grid's Nyquist frequency")
    assert "keeping 23 % of its roll-off" in warned_bad[0] and "a pixel of at most 0.516 µm" in warned_bad[0]


def test_undersampled_pupil_gives_one_warning() -> None:
    """Beyond λ/(2·NA) the pupil warning says it all: the band-limit warning is not repeated."""
    plan = plan_for_sources(_optics(pixel_size_um=0.65), (32, 32), SOURCES, warn=False)
    assert len(plan.warnings) == 1 and "undersamples the pupil" in plan.warnings[0]


# -- silent on what we ship, and before any computation ---------------------------------------------------


def test_shipped_geometries_plan_silently() -> None:
    from napari_fdt.data.io import read_acquisition

    acq = read_acquisition(ROOT / "sample_data" / "letters")
    o8 = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=8, slice_spacing_um=2.0)
    o6 = dataclasses.replace(o8, n_slices=6)
    with warnings.catch_warnings():
        warnings.simplefilter("error", FDTWarning)
        plan_for_sources(acq.optics, acq.image_shape, acq.sources_um)  # bundled sample
        plan_for_sources(o8, (96, 96), source_grid(8, 0.8 * 96 * 0.33, 40.0))  # fdt simulate's defaults
        plan_for_sources(o6, (48, 48), source_grid(4, 0.8 * 48 * 0.33, 20.0))  # napari's beads sample


def test_reconstructor_warns_at_construction(capsys, tmp_path) -> None:
    """The run's sampling problems are reported when the solver is built, before it computes anything."""
    from napari_fdt.cli import main
    from napari_fdt.data.acquisition import Acquisition
    from napari_fdt.data.io import write_acquisition
    from napari_fdt.recon.run.solver import Reconstructor

    optics = _optics(pixel_size_um=0.55)
    rng = np.random.default_rng(0)
    acq = Acquisition(images=(1.0 + rng.random((3, 30, 30))).astype(np.float32), optics=optics, sources_um=SOURCES)
    with pytest.warns(FDTWarning, match=r"^pixel_size_um 0.55: the grid's Nyquist frequency"):
        rec = Reconstructor(acq, device="cpu")
    assert rec.completed_stages == 0 and rec.volume is None
    write_acquisition(acq, tmp_path / "acq")
    assert main(["info", str(tmp_path / "acq")]) == 0
    assert "warning: pixel_size_um 0.55: the grid's Nyquist frequency" in capsys.readouterr().err
