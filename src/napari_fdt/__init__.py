"""napari-fdt: fluorescence diffraction tomography, headless core and napari plugin.

The public API: read an acquisition, reconstruct its RI volume (``Reconstructor`` / ``reconstruct`` with a
``SolverConfig``), write the result with its report; simulate test scenes; the forward model on its own.
The core (everything but :mod:`napari_fdt.napari`) imports no Qt. Lengths are in micrometres. The layers of the
package: docs/architecture.md.
"""

from __future__ import annotations

from napari_fdt._version import __version__
from napari_fdt.data.acquisition import Acquisition
from napari_fdt.data.io import read_acquisition, read_volume_tiff, write_acquisition, write_volume_tiff
from napari_fdt.device import resolve_device
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.render import render_images
from napari_fdt.physics.grid import GridPlan, plan_for_sources, plan_grid
from napari_fdt.physics.optics import Optics
from napari_fdt.recon.run.report import build_report, write_result
from napari_fdt.recon.run.solver import Reconstructor, Snapshot, reconstruct
from napari_fdt.recon.settings.config import SolverConfig, StageConfig, load_config
from napari_fdt.sim.simulate import Simulation, make_scene, simulate, source_grid

__all__ = [
    "__version__",
    "Acquisition",
    "FDTInputError",
    "FDTWarning",
    "GridPlan",
    "MultiSliceModel",
    "Optics",
    "Reconstructor",
    "Simulation",
    "Snapshot",
    "SolverConfig",
    "StageConfig",
    "build_report",
    "load_config",
    "make_scene",
    "plan_for_sources",
    "plan_grid",
    "read_acquisition",
    "read_volume_tiff",
    "reconstruct",
    "render_images",
    "resolve_device",
    "simulate",
    "source_grid",
    "write_acquisition",
    "write_result",
    "write_volume_tiff",
]
