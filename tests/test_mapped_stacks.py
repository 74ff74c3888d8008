"""Full-size stacks opened lazily (issue 28, item 3): memory maps, chunked checks, pickling by reference, and the
resident memory of ``fdt info`` on a stack far larger than what it may hold."""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from napari_fdt.data import mapped
from napari_fdt.data.acquisition import Acquisition
from napari_fdt.data.io import read_acquisition, write_acquisition
from napari_fdt.data.microscope import read_stack
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.physics.optics import Optics

OPTICS = dict(wavelength_um=0.6, n_background=1.33, na=0.65, pixel_size_um=0.33, n_slices=4, slice_spacing_um=1.5,
              image_plane_um=0.0)


def _folder(path: Path, images: np.ndarray, *, compression: str | None = None) -> Path:
    """An acquisition folder with ``images`` (N, H, W) written as one TIFF series (optionally compressed)."""
    path.mkdir(parents=True)
    n = images.shape[0]
    g = np.linspace(-5, 5, n)
    meta = {"format": "fdt-acquisition", "version": 1, "images": "images.tif", **OPTICS,
            "sources_um": [[float(x), 0.0, 20.0] for x in g]}
    (path / "acquisition.json").write_text(json.dumps(meta))
    tifffile.imwrite(path / "images.tif", images, photometric="minisblack", compression=compression)
    return path


def test_uncompressed_stack_is_mapped_read_only_and_compressed_one_read(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    images = rng.integers(0, 4000, size=(6, 32, 40), dtype=np.uint16)
    plain = read_acquisition(_folder(tmp_path / "plain", images))
    packed = read_acquisition(_folder(tmp_path / "packed", images, compression="zlib"))
    assert isinstance(plain.images, np.memmap) and not plain.images.flags.writeable
    assert not isinstance(packed.images, np.memmap)
    np.testing.assert_array_equal(plain.images, images)
    np.testing.assert_array_equal(packed.images, images)
    # the bare-stack reader of the napari plugin maps the same way
    bare = read_stack(tmp_path / "plain" / "images.tif").images
    assert isinstance(bare, np.memmap)
    np.testing.assert_array_equal(bare, images)


def test_mapped_acquisition_pickles_as_a_file_reference(tmp_path: Path) -> None:
    images = np.random.default_rng(1).random((20, 64, 64), dtype=np.float32)
    acq = read_acquisition(_folder(tmp_path / "a", images))
    blob = pickle.dumps(acq)
    assert len(blob) < 10_000 < images.nbytes  # the pixels are not in it
    back = pickle.loads(blob)
    assert isinstance(back.images, np.memmap)
    np.testing.assert_array_equal(back.images, images)
    # a view of the map (a subset of the images) points at its own first image in the file
    ref = mapped.mapped_file(acq.images[7:11])
    assert ref is not None and ref.shape == (4, 64, 64)
    np.testing.assert_array_equal(ref.open(), images[7:11])
    # an array in memory pickles its pixels, as before
    in_memory = Acquisition(images=np.array(images), optics=acq.optics, sources_um=acq.sources_um)
    assert len(pickle.dumps(in_memory)) > images.nbytes


def test_chunked_checks_find_nan_and_negative_pixels_in_any_chunk(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(mapped, "CHUNK_BYTES", 2 * 16 * 16 * 4)  # two images per chunk
    images = np.ones((9, 16, 16), dtype=np.float32)
    images[7, 3, 4] = np.nan
    images[8, 0, 0] = np.inf
    with pytest.raises(FDTInputError) as err:
        read_acquisition(_folder(tmp_path / "nan", images))
    assert err.value.field == "images"
    assert "2 non-finite pixels" in str(err.value) and "first at image 7, row 3, col 4" in str(err.value)
    images = np.ones((9, 16, 16), dtype=np.float64)
    images[5, 1, 1] = -2.0
    images[1, 2, 2] = -1.0
    with pytest.warns(FDTWarning, match="2 negative pixels"):
        acq = Acquisition(images=images, optics=Optics(**OPTICS))
    assert acq.images.dtype == np.float32
    np.testing.assert_array_equal(acq.images, images.astype(np.float32))


def test_scaled_copy_equals_the_whole_array_computation(monkeypatch) -> None:
    monkeypatch.setattr(mapped, "CHUNK_BYTES", 3 * 8 * 8 * 4)
    images = np.random.default_rng(2).integers(0, 60000, size=(10, 8, 8), dtype=np.uint16)
    mean = mapped.mean_of(images)
    assert mean == pytest.approx(images.astype(np.float64).mean(), rel=1e-12)
    np.testing.assert_array_equal(mapped.scaled_float32(images, mean), images.astype(np.float32) / np.float32(mean))


def _peak_rss_mb(code: list[str]) -> float:
    """Peak resident memory (MB) of a child process running ``code``."""
    probe = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True, stdout=subprocess.DEVNULL); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)")
    out = subprocess.run([sys.executable, "-c", probe, *code], check=True, capture_output=True, text=True)
    return float(out.stdout.strip().splitlines()[-1])


def test_fdt_info_reads_no_pixels_of_a_large_stack(tmp_path: Path) -> None:
    """The full-size stack (1521 × 512², 0.8 GB) peaks at 236 MB in `fdt info` (docs/hard_cases.md); here a 192 MB
    stack must add less than a quarter of its size to what the imports alone hold."""
    n, side = 384, 512
    folder = tmp_path / "big"
    folder.mkdir()
    g = np.linspace(-40, 40, n)
    meta = {"format": "fdt-acquisition", "version": 1, "images": "images.tif", **OPTICS,
            "sources_um": [[float(x), 0.0, 50.0] for x in g]}
    (folder / "acquisition.json").write_text(json.dumps(meta))
    block = np.random.default_rng(3).integers(100, 4000, size=(side, side), dtype=np.uint16)
    with tifffile.TiffWriter(folder / "images.tif") as tw:
        for _ in range(n):
            tw.write(block, contiguous=True, photometric="minisblack")
    stack_mb = n * side * side * 2 / 2**20
    imports = _peak_rss_mb([sys.executable, "-c", "import napari_fdt.cli, napari_fdt.data.io, napari_fdt.physics.grid"])
    info = _peak_rss_mb([sys.executable, "-c", "import sys; from napari_fdt.cli import main; sys.exit(main(sys.argv[1:]))",
                         "info", str(folder)])
    assert info - imports < 0.25 * stack_mb, (info, imports, stack_mb)


def test_write_then_read_round_trip_keeps_pixels(tmp_path: Path) -> None:
    images = np.random.default_rng(4).integers(0, 4000, size=(5, 24, 24), dtype=np.uint16)
    acq = Acquisition(images=images, optics=Optics(**OPTICS), sources_um=[[0.0, 0.0, 10.0 + i] for i in range(5)])
    back = read_acquisition(write_acquisition(acq, tmp_path / "out"))
    assert isinstance(back.images, np.memmap)
    np.testing.assert_array_equal(back.images, images)
