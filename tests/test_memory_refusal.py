"""Runs too large for the memory are refused before anything is allocated: ``fdt forward``, ``fdt simulate`` and
the acquisition reader (``napari_fdt.model.memory.forward_bytes``, ``benchmarks/forward_memory.py``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

import napari_fdt.device as device_module
import napari_fdt.model.forward as forward_module
from napari_fdt.cli import _HOST_BYTES_PER_IMAGE_PIXEL, main
from napari_fdt.data.io import read_acquisition, write_acquisition, write_volume_tiff
from napari_fdt.errors import FDTInputError
from napari_fdt.model.memory import forward_bytes
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.optics import Optics
from napari_fdt.sim.simulate import simulate, source_grid

ROOT = Path(__file__).resolve().parents[1]
OPTICS = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=4, slice_spacing_um=2.0)


def test_forward_bytes_bounds_the_measured_peak() -> None:
    """The estimate is an upper bound of the peak measured on CPU, and not a loose one (within 3×).

    Measured by ``benchmarks.forward_memory.measure`` in a fresh process (a peak is only clean there), imported."""
    measure = "import json; from benchmarks.forward_memory import measure; print(json.dumps(measure(1024, 4, 4, 'cpu')))"
    out = subprocess.run([sys.executable, "-c", measure], capture_output=True, text=True, check=True, timeout=300, cwd=ROOT)
    measured = json.loads(out.stdout.strip().splitlines()[-1])
    estimate = forward_bytes((1024, 1024), 4, 4)
    assert estimate / 3 < measured <= estimate, (measured, estimate)
    # inference memory does not grow with the slices, except for the padded volume (4 bytes per pixel per slice)
    assert forward_bytes((1024, 1024), 64, 4) - forward_bytes((1024, 1024), 4, 4) == 4 * 1024 * 1024 * 60


def test_training_bytes_bound_the_measured_step_with_pixel_integration() -> None:
    """The finest stage's estimate (the memory check's and ``fdt plan``'s) bounds a training step measured on CPU with the
    camera's pixel integration on, within 3×: the sample on the full window (before the pixel means were counted the
    estimate was 338 MiB for a step measured at 503-594 MiB). Measured by ``benchmarks.training_memory`` in a fresh
    process."""
    from benchmarks.training_memory import measure_in_fresh_process

    r = measure_in_fresh_process(str(ROOT / "sample_data" / "letters"), True, "full")
    assert r["model"] == "MultiSliceModel" and r["batch"] == 16, r
    assert r["measured_bytes"] <= r["estimate_bytes"] < 3 * r["measured_bytes"], r


def test_the_estimate_holds_the_coherence_masks() -> None:
    """With ``coherence`` "mask" the finest stage holds every image's mask, (N, H, W) float32, for the whole stage: the
    estimate counts them (before, a full-size stack's 1.6 GB of masks were not in it)."""
    import dataclasses

    from napari_fdt.recon.problem.preflight import coherence_mask_bytes, finest_stage_bytes
    from napari_fdt.recon.settings.config import SolverConfig

    acq = read_acquisition(ROOT / "sample_data" / "letters")
    src = acq.sources_um
    plain, masked = SolverConfig(coherence="none"), SolverConfig(coherence="mask")
    n, (h, w) = acq.n_images, acq.image_shape
    assert coherence_mask_bytes(acq, plain) == 0 and coherence_mask_bytes(acq, masked) == 4 * n * h * w
    for device in ("cpu", "cuda"):
        diff = finest_stage_bytes(acq, masked, src, 1, device)[0] - finest_stage_bytes(acq, plain, src, 1, device)[0]
        assert diff == 4 * n * h * w
    coarse = dataclasses.replace(masked, stages=[masked.stages[0]])  # a run whose finest stage is x4
    assert coherence_mask_bytes(acq, coarse) == 4 * n * (h // 4) * (w // 4)


@pytest.fixture()
def clean_acquisition(tmp_path):
    """A noise-free acquisition with exact sources and gains 1, and its true RI volume."""
    sim = simulate(np.zeros((4, 32, 32), np.float32) + 0.01 * np.eye(32, dtype=np.float32), OPTICS,
                   source_grid(3, 8.0, 15.0), noise=False, brightness_spread=0.0, jitter_xy_um=0.0, jitter_depth_um=0.0,
                   device="cpu")
    folder = write_acquisition(sim.acquisition, tmp_path / "acq")
    write_volume_tiff(tmp_path / "ri.tif", sim.ri, (2.0, 0.33, 0.33))
    return sim, folder, tmp_path / "ri.tif"


def _limit_memory(monkeypatch, free_bytes: int) -> None:
    monkeypatch.setattr(device_module, "available_bytes", lambda device: int(free_bytes))


def _no_model(monkeypatch) -> list:
    built = []

    class Sentinel(forward_module.MultiSliceModel):
        def __init__(self, *a, **k):
            built.append(1)
            super().__init__(*a, **k)

    monkeypatch.setattr(forward_module, "MultiSliceModel", Sentinel)
    return built


def test_fdt_forward_refuses_a_batch_that_does_not_fit(monkeypatch, capsys, clean_acquisition, tmp_path) -> None:
    sim, folder, ri = clean_acquisition
    plan = plan_for_sources(OPTICS, (32, 32), sim.acquisition.sources_um, warn=False)
    host = _HOST_BYTES_PER_IMAGE_PIXEL * 9 * 32 * 32 + 12 * 4 * 32 * 32
    _limit_memory(monkeypatch, host + forward_bytes(plan.padded_shape, 4, 3) / 0.9 + 1)  # three images fit, four do not
    built = _no_model(monkeypatch)
    assert main(["forward", str(folder), "--ri", str(ri), "--batch-size", "8", "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: batch_size: a batch of 8 images needs about")
    assert err[0].endswith("(lower --batch-size to 3)") and f"{plan.padded_shape[0]}x{plan.padded_shape[1]} window" in err[0]
    assert built == []  # refused before the model was built
    # the advice works, and the images are right: the true volume reproduces the noise-free images
    out = tmp_path / "pred.tif"
    assert main(["forward", str(folder), "--ri", str(ri), "--batch-size", "3", "--device", "cpu", "--out", str(out)]) == 0
    assert "relative residual after a per-image gain: 0.0000 overall" in capsys.readouterr().out
    pred = tifffile.imread(out)
    assert np.allclose(pred, sim.acquisition.images, rtol=1e-4, atol=1e-4 * float(pred.max()))


def test_fdt_forward_refuses_an_image_too_large_for_the_device(monkeypatch, capsys, clean_acquisition) -> None:
    _, folder, ri = clean_acquisition
    _limit_memory(monkeypatch, 2_000_000)  # 2 MB: the results (0.5 MB) fit, one image's fields (several MB) do not
    built = _no_model(monkeypatch)
    assert main(["forward", str(folder), "--ri", str(ri), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: images: one image of 32x32 px needs about")
    assert "crop or bin the images" in err[0] and built == []


def test_fdt_simulate_lowers_its_batch_or_refuses_the_shape(monkeypatch, capsys, tmp_path) -> None:
    args = ["simulate", "beads", None, "--shape", "32", "32", "--n-slices", "4", "--sources", "3", "--device", "cpu",
            "--no-noise"]
    assert main([a if a else str(tmp_path / "full") for a in args]) == 0
    plan = plan_for_sources(OPTICS, (32, 32), source_grid(3, 0.8 * 32 * 0.33, 40.0), warn=False)
    host = _HOST_BYTES_PER_IMAGE_PIXEL * 9 * 32 * 32 + 8 * 4 * 32 * 32
    _limit_memory(monkeypatch, host + forward_bytes(plan.padded_shape, 4, 2) / 0.9 + 1)  # two images at a time
    capsys.readouterr()
    assert main([a if a else str(tmp_path / "small") for a in args]) == 0
    assert "; 2 images at a time (memory);" in capsys.readouterr().out
    a = read_acquisition(tmp_path / "full").images
    b = read_acquisition(tmp_path / "small").images
    assert np.allclose(a, b, rtol=1e-5, atol=1e-5 * float(a.max()))  # same images, computed two at a time
    _limit_memory(monkeypatch, (host + 1000) / 0.9)  # the results fit, one image's fields do not
    capsys.readouterr()
    assert main([a if a else str(tmp_path / "none") for a in args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: shape: one image of 32x32 px needs about")
    assert not (tmp_path / "none").exists()


def test_reader_refuses_a_tiff_whose_header_claims_a_huge_stack(tmp_path, capsys) -> None:
    """A (corrupt or absurd) header of 2 images of 10⁶×10⁶ px: refused from the header, nothing read."""
    folder = tmp_path / "acq"
    folder.mkdir()
    tifffile.imwrite(folder / "images.tif", np.ones((2, 16, 16), np.uint16), photometric="minisblack")
    with tifffile.TiffFile(folder / "images.tif", mode="r+b") as tif:
        for page in tif.pages:
            page.tags["ImageWidth"].overwrite(10**6)
            page.tags["ImageLength"].overwrite(10**6)
    meta = {"format": "fdt-acquisition", "version": 1, "images": "images.tif", "wavelength_um": 0.635,
            "n_background": 1.33, "na": 0.8, "pixel_size_um": 0.33, "n_slices": 4, "slice_spacing_um": 2.0}
    (folder / "acquisition.json").write_text(json.dumps(meta))
    with pytest.raises(FDTInputError, match=r"^images: images.tif holds 2 images of 1000000 x 1000000 px \(uint16\)") as exc:
        read_acquisition(folder)
    assert exc.value.fix.startswith("crop or bin the images")
    assert main(["info", str(folder)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert len(err) == 1 and "GiB of memory are free" in err[0]
