"""napari-fdt: fluorescence diffraction tomography, headless core and napari plugin.

The core (this package minus the widget layer) imports no Qt. Lengths are in micrometres.
"""

from __future__ import annotations

__version__ = "0.1.0"

from .acquisition import Acquisition
from .errors import FDTInputError, FDTWarning
from .forward import MultiSliceModel, resolve_device
from .grid import GridPlan, plan_for_sources, plan_grid
from .io import read_acquisition, read_volume_tiff, write_acquisition, write_volume_tiff
from .optics import Optics
from .simulate import Simulation, make_scene, render_images, simulate, source_grid

__all__ = [
    "__version__",
    "Acquisition",
    "FDTInputError",
    "FDTWarning",
    "GridPlan",
    "MultiSliceModel",
    "Optics",
    "Simulation",
    "make_scene",
    "plan_for_sources",
    "plan_grid",
    "read_acquisition",
    "read_volume_tiff",
    "render_images",
    "resolve_device",
    "simulate",
    "source_grid",
    "write_acquisition",
    "write_volume_tiff",
]
