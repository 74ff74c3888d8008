"""Microscope files and RI volumes opened and saved through a real (hidden) napari viewer: npe2 picks the reader from
the manifest's patterns, a list of per-source files reaches the reader as a stack, the writer refuses image stacks.

Needs napari, a Qt binding, pytest-qt and an X display (``bash scripts/test.sh`` runs under ``xvfb-run``).
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest
import tifffile

pytest.importorskip("napari")
pytest.importorskip("pytestqt")
pytest.importorskip("qtpy")
if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
    pytest.skip("napari needs a display: run the tests under xvfb-run (bash scripts/test.sh)", allow_module_level=True)

from napari_fdt.errors import FDTWarning  # noqa: E402
from napari_fdt.napari.layers import META_FILE_OPTICS, META_KIND, META_REPORT, stack_images  # noqa: E402

PLUGIN = "napari-fdt"


def test_imagej_stack_opens_with_its_scale_and_file_optics(make_napari_viewer, tmp_path) -> None:
    data = np.arange(4 * 16 * 20, dtype=np.uint16).reshape(4, 16, 20)
    tifffile.imwrite(tmp_path / "ij.tif", data, imagej=True, resolution=(1 / 0.4, 1 / 0.4), metadata={"unit": "micron", "axes": "TYX"})
    viewer = make_napari_viewer()
    [layer] = viewer.open(str(tmp_path / "ij.tif"), plugin=PLUGIN)
    assert np.array_equal(stack_images(layer.data), data) and np.allclose(layer.scale[2:], 0.4)  # (N, 1, H, W): image axis
    assert layer.metadata[META_FILE_OPTICS] == pytest.approx({"pixel_size_um": 0.4})
    assert np.allclose(layer.translate[2:], (-8 * 0.4, -10 * 0.4))


def test_per_source_files_open_as_one_stack(make_napari_viewer, tmp_path) -> None:
    files = []
    for i in range(3):
        files.append(str(tmp_path / f"src_{i}.tif"))
        tifffile.imwrite(files[-1], np.full((16, 16), i + 1, np.float32))
    viewer = make_napari_viewer()
    [layer] = viewer.open(files, stack=True, plugin=PLUGIN)
    images = stack_images(layer.data)
    assert images.shape == (3, 16, 16) and list(images[:, 0, 0]) == [1, 2, 3]
    assert layer.metadata[META_KIND] == "stack" and layer.metadata[META_FILE_OPTICS] == {}


def test_our_reader_is_offered_only_for_what_it_reads(tmp_path) -> None:
    from npe2 import PluginManager

    pm = PluginManager.instance()
    tifffile.imwrite(tmp_path / "a.tif", np.zeros((2, 16, 16), np.float32))
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "other.json").write_text("{}")
    offered = {p: {r.plugin_name for r in pm.iter_compatible_readers([str(tmp_path / p)])} for p in ("a.tif", "notes.txt", "other.json")}
    assert PLUGIN in offered["a.tif"] and PLUGIN not in offered["notes.txt"] and PLUGIN not in offered["other.json"]


def test_save_layers_refuses_an_image_stack_and_writes_an_ri_volume(make_napari_viewer, tmp_path) -> None:
    viewer = make_napari_viewer()
    stack = viewer.add_image(np.ones((4, 16, 16), np.float32), name="cells", metadata={META_KIND: "stack"})
    viewer.layers.selection = {stack}
    # napari swallows the writer's error when it picks the writer itself: the refusal reaches the user as a warning
    with pytest.warns(FDTWarning, match="cells is an image stack, not an RI volume"):
        assert viewer.layers.save(str(tmp_path / "cells.tif"), selected=True, plugin=PLUGIN) == []
    assert not (tmp_path / "cells.tif").exists()
    report = {"format": "napari-fdt-report", "version": 1, "ri": {"voxel_size_um": [2.0, 0.33, 0.33]}}
    ri = viewer.add_image(np.full((3, 16, 16), 1.35, np.float32), name="RI", scale=(2.0, 0.33, 0.33), metadata={META_KIND: "ri", META_REPORT: report})
    viewer.layers.selection = {ri}
    written = viewer.layers.save(str(tmp_path / "RI_lr0.05.tif"), selected=True, plugin=PLUGIN)
    assert sorted(map(str, written)) == sorted([str(tmp_path / "RI_lr0.05.tif"), str(tmp_path / "RI_lr0.05.json")])
