"""Shared set-up of the napari plugin tests (tests/test_napari_plugin*.py): the skip where napari or a display is
missing, and the helpers that open, dock and run (the scene ``tiny_sim``/``tiny_dir`` and napari's ``notifications``
are fixtures of tests/conftest.py)."""

from __future__ import annotations

import dataclasses
import os
import sys

import pytest

pytest.importorskip("napari")
pytest.importorskip("pytestqt")
pytest.importorskip("qtpy")
if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    pytest.skip("napari needs a display: run the tests under xvfb-run (bash scripts/test.sh)", allow_module_level=True)

from napari.layers import Image, Points  # noqa: E402
from napari.utils.notifications import notification_manager  # noqa: E402

from napari_fdt import Acquisition, FDTWarning, Optics, simulate, source_grid, write_acquisition  # noqa: E402
from napari_fdt.data.io import read_volume_tiff  # noqa: E402
from napari_fdt.napari.layers import META_ACQUISITION, META_KIND, META_REPORT  # noqa: E402
from napari_fdt.napari.widgets.widget_acquisition import AcquisitionWidget  # noqa: E402
from napari_fdt.napari.widgets.widget_reconstruction import ReconstructionWidget  # noqa: E402
from napari_fdt.recon.settings.config import SolverConfig, load_config  # noqa: E402
from napari_fdt.sim.phantoms import text_phantom  # noqa: E402

# what the test modules take from here: the helpers below, and the names they need once napari is known to import
__all__ = ["PLUGIN", "_open", "_docked", "_settings", "_wait_done", "_wait_tasks", "tiny_sim_optics", "Image", "Points",
           "notification_manager", "Acquisition", "FDTWarning", "Optics", "simulate", "source_grid", "write_acquisition",
           "read_volume_tiff", "META_ACQUISITION", "META_KIND", "META_REPORT", "AcquisitionWidget", "ReconstructionWidget",
           "SolverConfig", "load_config", "text_phantom"]

PLUGIN = "napari-fdt"


def _open(viewer, path):
    layers = viewer.open(str(path), plugin=PLUGIN)
    return layers[0]


def _docked(viewer, widget):
    viewer.window.add_dock_widget(widget, name=type(widget).__name__)
    return widget


def _settings(widget: ReconstructionWidget, stages: str, final_stage_min_passes: float = 0.0) -> None:
    """Small runs of exactly ``stages`` (``final_stage_min_passes`` 0: the finest stage is not lengthened)."""
    widget.set_config(dataclasses.replace(widget.config(), final_stage_min_passes=final_stage_min_passes))
    widget.stages.value = stages
    widget.batch_size.value = 4
    widget.snapshot_every.value = 1
    widget.device.value = "cpu"


def _wait_done(qtbot, widget, timeout_ms=120_000):
    qtbot.waitUntil(lambda: not widget.running and widget._worker is None, timeout=timeout_ms)


def _wait_tasks(qtbot, widget, timeout_ms=60_000):
    """Until the widget's background actions (fit, previews, save, comparison) have ended and shown their result."""
    qtbot.waitUntil(lambda: widget.tasks.idle, timeout=timeout_ms)


def tiny_sim_optics() -> Optics:
    """The registry's tiny scene's optics (``benchmarks.scenes.tiny_optics``)."""
    from benchmarks.scenes import tiny_optics

    return tiny_optics()
