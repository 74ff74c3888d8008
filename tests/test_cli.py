"""The ``fdt`` command line end to end: simulate, info, forward; errors exit non-zero without a traceback."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from napari_fdt.cli import main
from napari_fdt.data.io import read_acquisition

SMALL = ["--shape", "40", "48", "--n-slices", "4", "--slice-spacing-um", "2", "--sources", "3", "--depth-um", "20"]


def test_simulate_writes_a_consistent_acquisition(tmp_path: Path, capsys) -> None:
    out = tmp_path / "acq"
    assert main(["simulate", "letters", str(out), *SMALL, "--seed", "5"]) == 0
    acq = read_acquisition(out)
    assert acq.images.shape == (9, 40, 48) and acq.images.dtype == np.float32
    assert acq.optics.n_slices == 4 and acq.optics.pixel_size_um == pytest.approx(0.33)
    truth = json.loads((out / "ground_truth_sources_um.json").read_text())
    true_src = np.array(truth["sources_um"])
    assert true_src.shape == (9, 3) and np.all(true_src[:, 2] == 20.0)
    # The grid spans 80 % of the smaller side of the field of view, centred.
    span = 0.8 * 40 * 0.33
    assert true_src[:, 0].min() == pytest.approx(-span / 2) and true_src[:, 0].max() == pytest.approx(span / 2)
    # Initial estimates are jittered by about 1 µm RMS per axis, not copied.
    err = acq.sources_um - true_src
    assert 0.3 < np.sqrt(np.mean(err**2)) < 2.0
    with tifffile.TiffFile(out / "ground_truth_ri.tif") as tif:
        ri = tif.asarray()
        assert tif.is_ome
    assert ri.shape == (4, 40, 48)
    assert ri.min() == pytest.approx(1.33) and ri.max() == pytest.approx(1.38, abs=1e-4)
    # Noise: the images are counts near the requested mean with Poisson statistics.
    assert abs(acq.images.mean() / 2000.0 - 1) < 0.35


def test_forward_reproduces_noise_free_simulation(tmp_path: Path, capsys) -> None:
    out = tmp_path / "acq"
    assert main(["simulate", "beads", str(out), *SMALL, "--no-noise", "--jitter-um", "0"]) == 0
    pred = tmp_path / "pred.tif"
    assert main(["forward", str(out), "--ri", str(out / "ground_truth_ri.tif"), "--out", str(pred), "--device", "cpu"]) == 0
    text = capsys.readouterr().out
    overall = float(text.split("relative residual after a per-image gain: ")[1].split()[0])
    assert overall < 1e-4  # float32 rounding only: writer, reader and model agree
    fitted = tifffile.imread(pred)
    meas = tifffile.imread(out / "images.tif")
    assert np.linalg.norm(fitted - meas) / np.linalg.norm(meas) < 1e-4


def test_info_reports_the_window(tmp_path: Path, capsys) -> None:
    out = tmp_path / "acq"
    assert main(["simulate", "cells", str(out), *SMALL]) == 0
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "9 images of 40x48 px" in text and "forward window" in text
    assert "of the depth of field" in text  # the thin screens' criterion (docs/physics.md, "Sub-slices")
    assert "field grid: the camera's pixels hold waves up to" in text  # the camera grid's (docs/physics.md)


def test_depth_of_field_is_the_pupil_edge_rays_defocus_scale() -> None:
    """λ/(n_b·(1 − cos θ)), sin θ = NA/n_b: 2.37 µm for the suite's optics (λ 0.635 µm, n_b 1.33, NA 0.8)."""
    import math

    from napari_fdt import Optics

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=8, slice_spacing_um=2.0)
    cos = math.sqrt(1 - (0.8 / 1.33) ** 2)
    assert o.depth_of_field_um == pytest.approx(0.635 / (1.33 * (1 - cos)), rel=1e-12)
    assert 2.36 < o.depth_of_field_um < 2.38


def test_user_errors_exit_2_with_the_field_named(tmp_path: Path, capsys) -> None:
    out = tmp_path / "acq"
    assert main(["simulate", "letters", str(out), *SMALL, "--na", "1.4"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: na:") and "n_background" in err
    assert not out.exists()
    assert main(["simulate", "letters", str(out), *SMALL]) == 0
    assert main(["simulate", "letters", str(out), *SMALL]) == 2
    assert "exists" in capsys.readouterr().err
    assert main(["forward", str(tmp_path / "missing"), "--ri", str(out / "ground_truth_ri.tif")]) == 2
    # A volume of the wrong shape is refused before any computation.
    bad = tmp_path / "bad.tif"
    tifffile.imwrite(bad, np.full((3, 40, 48), 1.33, np.float32))
    assert main(["forward", str(out), "--ri", str(bad)]) == 2
    assert "ri: volume shape" in capsys.readouterr().err


def test_console_error_has_no_traceback(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "napari_fdt", "simulate", "letters", str(tmp_path / "x"), "--pixel-size-um", "-1"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip() == "error: pixel_size_um: must be positive, got -1 (give it in µm, > 0)"


def test_warning_printed_for_undersampled_pupil(tmp_path: Path, capsys) -> None:
    out = tmp_path / "acq"
    assert main(["simulate", "letters", str(out), *SMALL, "--na", "1.0", "--pixel-size-um", "0.4"]) == 0
    assert "warning: pixel_size_um 0.4 undersamples the pupil" in capsys.readouterr().err


def test_simulate_with_emission_bandwidth_records_it(tmp_path: Path, capsys) -> None:
    out = tmp_path / "acq"
    args = ["simulate", "beads", str(out), *SMALL, "--no-noise", "--jitter-um", "0"]
    assert main([*args, "--bandwidth-um", "0.04", "--n-wavelengths", "5"]) == 0
    assert "emission FWHM 40 nm in 5 wavelengths, coherence length 7.6 µm" in capsys.readouterr().out
    settings = json.loads((out / "acquisition.json").read_text())["simulated"]
    assert settings["bandwidth_um"] == 0.04 and settings["n_wavelengths"] == 5
    lam, w = np.array(settings["emission_wavelengths_um"]), np.array(settings["emission_weights"])
    assert lam.shape == w.shape == (5,) and np.sum(w) == pytest.approx(1.0) and np.sum(w * lam) == pytest.approx(0.635)
    assert settings["coherence_length_um"] == pytest.approx(0.635**2 / (1.33 * 0.04))
    truth = json.loads((out / "ground_truth_sources_um.json").read_text())
    assert truth["settings"]["bandwidth_um"] == 0.04 and truth["settings"]["n_wavelengths"] == 5
    partial = read_acquisition(out).images
    # The coherent simulation of the same scene differs (fringes), but only by some per cent.
    coherent_dir = tmp_path / "coherent"
    assert main([*args[:2], str(coherent_dir), *args[3:]]) == 0
    settings0 = json.loads((coherent_dir / "acquisition.json").read_text())["simulated"]
    assert settings0["bandwidth_um"] == 0.0 and settings0["n_wavelengths"] == 9 and settings0["emission_wavelengths_um"] == [0.635]
    coherent = read_acquisition(coherent_dir).images
    rel = np.linalg.norm(partial - coherent) / np.linalg.norm(coherent)
    assert 1e-4 < rel < 0.2
    # Bad spectra are refused with the field named, before any output.
    bad = tmp_path / "bad"
    assert main(["simulate", "letters", str(bad), *SMALL, "--bandwidth-um", "-0.01"]) == 2
    assert capsys.readouterr().err.startswith("error: bandwidth_um:")
    assert main(["simulate", "letters", str(bad), *SMALL, "--bandwidth-um", "0.04", "--n-wavelengths", "0"]) == 2
    assert capsys.readouterr().err.startswith("error: n_wavelengths:")
    assert not bad.exists()
