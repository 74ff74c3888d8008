"""Check `fdt simulate` against an independent implementation of docs/physics.md.

The reference (`independent_reference.py`) is written from docs/format.md and docs/physics.md
only; the simulated folder is read here with tifffile and json, not with napari_fdt.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from tests import independent_reference as ref  # noqa: E402


def _simulate(out: Path, scene: str, *args: str) -> str:
    """Run `python -m napari_fdt simulate` (noise-free) and return its stdout."""
    cmd = [sys.executable, "-m", "napari_fdt", "simulate", scene, str(out), *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"{cmd} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def _read_folder(folder: Path):
    """Read images, optics, true RI, true sources and gains with tifffile/json only."""
    optics = json.loads((folder / "acquisition.json").read_text())
    images = np.asarray(tifffile.imread(folder / optics["images"]), dtype=np.float64)
    if images.ndim == 2:
        images = images[None]
    ri = np.asarray(tifffile.imread(folder / "ground_truth_ri.tif"), dtype=np.float64)
    truth = json.loads((folder / "ground_truth_sources_um.json").read_text())
    sources = np.asarray(truth["sources_um"], dtype=np.float64)
    gains = np.asarray(truth["gain"], dtype=np.float64)
    return optics, images, ri, sources, gains


def _check(folder: Path, stdout: str, n_images: int, shape: tuple[int, int], n_slices: int):
    optics, images, ri, sources, gains = _read_folder(folder)
    assert images.shape == (n_images, *shape)
    assert ri.shape == (n_slices, *shape)
    assert sources.shape == (n_images, 3) and gains.shape == (n_images,)

    # The CLI reports the window it used; the documented rule, applied to the true
    # sources, must give the same one.
    m = re.search(r"window (\d+)x(\d+) px", stdout)
    if m:
        win = ref.plan_window(optics, shape, sources)
        assert (win["Hp"], win["Wp"]) == (int(m.group(1)), int(m.group(2)))

    model = ref.forward_images(optics, ri, sources, gains)
    assert model.shape == images.shape and model.dtype == np.float64
    rel = np.linalg.norm(model - images) / np.linalg.norm(images)
    print(f"relative difference {rel:.3e}")
    assert rel < 1e-4, rel
    return rel


def test_letters_matches_independent_reference(tmp_path):
    folder = tmp_path / "acq"
    out = _simulate(folder, "letters", "--shape", "48", "40", "--n-slices", "4",
                    "--slice-spacing-um", "2", "--sources", "3", "--depth-um", "20",
                    "--no-noise", "--seed", "3")
    _check(folder, out, n_images=9, shape=(48, 40), n_slices=4)


def test_beads_odd_sizes_image_plane_matches_independent_reference(tmp_path):
    folder = tmp_path / "acq"
    out = _simulate(folder, "beads", "--shape", "37", "42", "--image-plane-um", "3",
                    "--na", "0.5", "--pixel-size-um", "0.4", "--sources", "2",
                    "--depth-um", "30", "--no-noise", "--seed", "3")
    optics = json.loads((folder / "acquisition.json").read_text())
    assert optics["image_plane_um"] == pytest.approx(3.0)
    assert optics["na"] == pytest.approx(0.5)
    assert optics["pixel_size_um"] == pytest.approx(0.4)
    _check(folder, out, n_images=4, shape=(37, 42), n_slices=int(optics["n_slices"]))
