"""napari sample data: the bundled letters acquisition and a small simulated bead scene.

Each returns the acquisition's image layer (with the :class:`~napari_fdt.data.acquisition.Acquisition` in its
metadata, ready for the widgets) and its ground-truth RI volume as a hidden layer, for comparison.

The bundled acquisition lives in the repository (``sample_data/letters``), found from the package's
location (an editable install, or ``NAPARI_FDT_SAMPLE_DIR``). Where it is absent (e.g. an installed wheel),
it is simulated again with the settings it was made with (``fdt simulate letters --seed 0``: same
scene, same seed), which takes a few seconds.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from napari_fdt.napari.layers import LayerDataTuple, acquisition_layer, ri_layer
from napari_fdt.physics.optics import Optics

__all__ = ["letters_sample", "simulated_beads", "sample_dir", "LETTERS_NAME", "BEADS_NAME"]

LETTERS_NAME = "Letters sample (64 images, 96×96, 8 slices)"
BEADS_NAME = "Simulated beads (16 images, 48×48, 6 slices)"


def sample_dir() -> Path | None:
    """``sample_data/letters`` of the repository holding this package, or ``$NAPARI_FDT_SAMPLE_DIR``; None if absent."""
    env = os.environ.get("NAPARI_FDT_SAMPLE_DIR")
    candidates = [Path(env)] if env else []
    here = Path(__file__).resolve()
    candidates += [parent / "sample_data" / "letters" for parent in here.parents[:4]]
    for c in candidates:
        if (c / "acquisition.json").is_file():
            return c
    return None


def _layers(acq, ri: np.ndarray | None, name: str, path: str | None) -> list[LayerDataTuple]:
    layer = acquisition_layer(acq, path=path, name=name)
    out = [layer]
    if ri is not None:
        data, kwargs, kind = ri_layer(ri, acq.optics, f"{name} ground truth RI", owner=layer[1]["metadata"]["fdt_id"])
        kwargs["visible"] = False
        kwargs["metadata"]["fdt_kind"] = "truth"  # not the "ri" layer a reconstruction updates
        out.append((data, kwargs, kind))
    return out


def letters_sample() -> list[LayerDataTuple]:
    """The bundled letters acquisition (64 images of 96×96 px, 8 slices), and its ground truth (hidden)."""
    from napari_fdt.data.io import read_acquisition, read_volume_tiff

    folder = sample_dir()
    if folder is not None:
        acq = read_acquisition(folder)
        truth = folder / "ground_truth_ri.tif"
        ri = read_volume_tiff(truth)[0] if truth.is_file() else None
        return _layers(acq, ri, "letters", str(folder))
    from napari_fdt.sim.simulate import make_scene, simulate, source_grid

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=8, slice_spacing_um=2.0)
    shape = (96, 96)
    sources = source_grid(8, 0.8 * shape[0] * o.pixel_size_um, 40.0)
    sim = simulate(make_scene("letters", shape, o, rng=0), o, sources, seed=0, device="cpu")
    return _layers(sim.acquisition, sim.ri, "letters", None)


def simulated_beads() -> list[LayerDataTuple]:
    """A small simulated scene: beads in 6 slices of 2 µm, 16 images of 48×48 px (seconds to reconstruct)."""
    from napari_fdt.sim.simulate import make_scene, simulate, source_grid

    o = Optics(wavelength_um=0.635, n_background=1.33, na=0.8, pixel_size_um=0.33, n_slices=6, slice_spacing_um=2.0)
    shape = (48, 48)
    sources = source_grid(4, 0.8 * shape[0] * o.pixel_size_um, 20.0)
    sim = simulate(make_scene("beads", shape, o, rng=0), o, sources, seed=0, device="cpu")
    return _layers(sim.acquisition, sim.ri, "beads", None)
