"""Microscope files in: OME-TIFF, ImageJ and plain TIFF stacks and per-source files, with the optics they state.

The files are made here with tifffile and hand-written OME-XML (the OME schema's own element and attribute names),
with known values in units other than µm, so the tests check the unit conversions and where each field is taken
from, not a copy of our own writer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile

from napari_fdt.data.microscope import natural_key, probe_stack, read_source_files, read_stack
from napari_fdt.errors import FDTInputError
from napari_fdt.napari.layers import META_FILE_OPTICS, META_NEEDS_OPTICS, stack_images
from napari_fdt.napari.reader import get_reader

N, H, W = 5, 24, 32

OME_XML = """<?xml version="1.0" encoding="UTF-8"?>
<OME xmlns="http://www.openmicroscopy.org/Schemas/OME/2016-06">
 <Instrument ID="Instrument:0">
  <Objective ID="Objective:0" LensNA="1.1" Immersion="Water" NominalMagnification="60"/>
  <Objective ID="Objective:1" LensNA="0.3" Immersion="Air" NominalMagnification="10"/>
 </Instrument>
 <Image ID="Image:0" Name="fdt">
  <InstrumentRef ID="Instrument:0"/>
  <ObjectiveSettings ID="Objective:0" RefractiveIndex="1.333"/>
  <Pixels ID="Pixels:0" DimensionOrder="XYZCT" Type="uint16" SizeX="{w}" SizeY="{h}" SizeZ="1" SizeC="1" SizeT="{n}"
          PhysicalSizeX="325" PhysicalSizeXUnit="nm" PhysicalSizeY="325" PhysicalSizeYUnit="nm">
   <Channel ID="Channel:0:0" SamplesPerPixel="1" EmissionWavelength="605"/>
   <TiffData IFD="0" PlaneCount="{n}"/>
  </Pixels>
 </Image>
</OME>"""


def _stack(dtype=np.uint16) -> np.ndarray:
    return (np.arange(N * H * W).reshape(N, H, W) % 1000).astype(dtype)


def _ome_file(path: Path, xml: str = OME_XML) -> np.ndarray:
    data = _stack()
    tifffile.imwrite(path, data, description=xml.format(n=N, h=H, w=W), metadata=None, photometric="minisblack")
    return data


def test_ome_tiff_gives_pixel_size_wavelength_na_and_index(tmp_path) -> None:
    data = _ome_file(tmp_path / "cells.ome.tif")
    head = probe_stack(tmp_path / "cells.ome.tif")
    assert head is not None and head.kind == "ome-tiff" and head.shape == (N, H, W)
    # 325 nm → 0.325 µm; 605 nm (OME's default unit) → 0.605 µm; NA of the referenced objective, not the other one
    assert head.optics == pytest.approx({"pixel_size_um": 0.325, "wavelength_um": 0.605, "na": 1.1, "n_background": 1.333})
    stack = read_stack(tmp_path / "cells.ome.tif")
    assert np.array_equal(stack.images, data) and stack.optics == head.optics


def test_ome_tiff_from_tifffile_metadata(tmp_path) -> None:
    """tifffile's own OME writer: sizes in µm and the channel's emission wavelength in µm; no objective → no NA."""
    data = _stack(np.float32)
    tifffile.imwrite(tmp_path / "t.ome.tif", data, ome=True, photometric="minisblack",
                     metadata={"axes": "TYX", "PhysicalSizeX": 0.2, "PhysicalSizeY": 0.2,
                               "Channel": {"Name": "GFP", "EmissionWavelength": 0.51, "EmissionWavelengthUnit": "µm"}})
    stack = read_stack(tmp_path / "t.ome.tif")
    assert stack.optics == pytest.approx({"pixel_size_um": 0.2, "wavelength_um": 0.51})
    assert np.array_equal(stack.images, data)


def test_imagej_tiff_gives_the_pixel_size_in_its_unit(tmp_path) -> None:
    data = _stack()
    tifffile.imwrite(tmp_path / "ij.tif", data, imagej=True, resolution=(1 / 0.45, 1 / 0.45), metadata={"unit": "micron", "axes": "TYX"})
    tifffile.imwrite(tmp_path / "ij_nm.tif", data, imagej=True, resolution=(1 / 450.0, 1 / 450.0), metadata={"unit": "nm", "axes": "ZYX"})
    for name in ("ij.tif", "ij_nm.tif"):
        stack = read_stack(tmp_path / name)
        assert stack.kind == "imagej-tiff" and stack.optics == pytest.approx({"pixel_size_um": 0.45}), name
        assert np.array_equal(stack.images, data)


def test_plain_tiff_states_nothing_unless_its_resolution_is_in_centimetres(tmp_path) -> None:
    data = _stack()
    tifffile.imwrite(tmp_path / "plain.tif", data, photometric="minisblack")
    tifffile.imwrite(tmp_path / "dpi.tif", data, photometric="minisblack", resolution=(72, 72), resolutionunit="INCH")
    tifffile.imwrite(tmp_path / "cm.tif", data, photometric="minisblack", resolution=(1e4 / 0.5, 1e4 / 0.5), resolutionunit="CENTIMETER")
    assert read_stack(tmp_path / "plain.tif").optics == {}
    assert read_stack(tmp_path / "dpi.tif").optics == {}  # 72 dpi is a printing default, not a pixel size
    assert read_stack(tmp_path / "cm.tif").optics == pytest.approx({"pixel_size_um": 0.5})


def test_napari_reader_puts_the_file_optics_on_the_stack_layer(tmp_path) -> None:
    _ome_file(tmp_path / "cells.ome.tif")
    reader = get_reader(str(tmp_path / "cells.ome.tif"))
    [(data, kwargs, kind)] = reader(str(tmp_path / "cells.ome.tif"))
    assert kind == "image" and data.shape == (N, 1, H, W)  # the image index on its own axis (docs/napari.md)
    meta = kwargs["metadata"]
    assert meta[META_FILE_OPTICS] == pytest.approx({"pixel_size_um": 0.325, "wavelength_um": 0.605, "na": 1.1, "n_background": 1.333})
    assert meta[META_NEEDS_OPTICS] is True  # the volume's sampling is never in a microscope file
    assert np.allclose(kwargs["scale"][2:], 0.325)
    assert np.allclose(kwargs["translate"][2:], (-(H // 2) * 0.325, -(W // 2) * 0.325))  # image-centred origin
    tifffile.imwrite(tmp_path / "plain.tif", _stack(), photometric="minisblack")
    [(_, kwargs, _)] = get_reader(str(tmp_path / "plain.tif"))(str(tmp_path / "plain.tif"))
    assert kwargs["metadata"][META_FILE_OPTICS] == {} and tuple(kwargs["scale"]) == (1.0, 1.0, 1.0, 1.0)


def test_per_source_files_in_natural_order(tmp_path) -> None:
    folder = tmp_path / "sources"
    folder.mkdir()
    for i in range(1, 12):  # img_1 … img_11: natural order puts img_2 before img_10
        tifffile.imwrite(folder / f"img_{i}.tif", np.full((H, W), i, np.uint16), imagej=True,
                         resolution=(1 / 0.3, 1 / 0.3), metadata={"unit": "um"})
    (folder / "notes.txt").write_text("not an image")
    stack = read_source_files(folder)
    assert stack.images.shape == (11, H, W) and list(stack.images[:, 0, 0]) == list(range(1, 12))
    assert stack.optics == pytest.approx({"pixel_size_um": 0.3})
    assert sorted(["a10", "a2", "a1"], key=natural_key) == ["a1", "a2", "a10"]
    # the napari reader: the folder, and a list of files in the order given
    [(data, kwargs, _)] = get_reader(str(folder))(str(folder))
    assert np.array_equal(stack_images(data), stack.images) and np.allclose(kwargs["scale"][2:], 0.3)
    files = [str(folder / f"img_{i}.tif") for i in (3, 1, 2)]
    [(data, _, _)] = get_reader(files)(files)
    assert list(stack_images(data)[:, 0, 0]) == [3, 1, 2]


def test_per_source_files_that_disagree_are_refused_or_left_empty(tmp_path) -> None:
    a, b, c = tmp_path / "a.tif", tmp_path / "b.tif", tmp_path / "c.tif"
    tifffile.imwrite(a, np.ones((H, W), np.uint16), imagej=True, resolution=(1 / 0.3, 1 / 0.3), metadata={"unit": "um"})
    tifffile.imwrite(b, np.ones((H, W), np.uint16), imagej=True, resolution=(1 / 0.4, 1 / 0.4), metadata={"unit": "um"})
    tifffile.imwrite(c, np.ones((H + 1, W), np.uint16))
    stack = read_source_files([a, b])
    assert "pixel_size_um" not in stack.optics and any("pixel_size_um" in n for n in stack.notes)
    with pytest.raises(FDTInputError, match=r"^images: c.tif is 25x32"):
        read_source_files([a, c])
    assert get_reader([str(a), str(c)]) is None


def test_get_reader_declines_what_it_cannot_read_from_the_header(tmp_path) -> None:
    tifffile.imwrite(tmp_path / "rgb.tif", np.zeros((H, W, 3), np.uint8), photometric="rgb")
    tifffile.imwrite(tmp_path / "ct.ome.tif", np.zeros((3, 2, H, W), np.uint16), ome=True, metadata={"axes": "TCYX"})
    tifffile.imwrite(tmp_path / "small.tif", np.zeros((4, 6, 6), np.float32))
    tifffile.imwrite(tmp_path / "complex.tif", np.zeros((2, H, W), np.complex64))
    (tmp_path / "fake.tif").write_bytes(b"this is not a TIFF at all")
    (tmp_path / "notes.json").write_text("{}")
    (tmp_path / "empty").mkdir()
    for name in ("rgb.tif", "ct.ome.tif", "small.tif", "complex.tif", "fake.tif", "notes.json", "empty", "missing.tif"):
        assert get_reader(str(tmp_path / name)) is None, name
    # the core says why, naming the field
    with pytest.raises(FDTInputError, match=r"^images: ct.ome.tif has axes TCYX"):
        read_stack(tmp_path / "ct.ome.tif")
    with pytest.raises(FDTInputError, match=r"^images: fake.tif is not a readable TIFF"):
        read_stack(tmp_path / "fake.tif")


def test_get_reader_reads_no_pixels(tmp_path, monkeypatch) -> None:
    """The decision comes from the header: get_reader never asks a series for its pixels."""
    _ome_file(tmp_path / "cells.ome.tif")
    calls = []
    original = tifffile.TiffPageSeries.asarray
    monkeypatch.setattr(tifffile.TiffPageSeries, "asarray", lambda self, *a, **k: calls.append(1) or original(self, *a, **k))
    assert get_reader(str(tmp_path / "cells.ome.tif")) is not None
    assert calls == []


def test_manifest_names_what_the_reader_reads() -> None:
    import yaml

    manifest = yaml.safe_load((Path(__file__).resolve().parents[1] / "src/napari_fdt/napari/napari.yaml").read_text(encoding="utf-8"))
    [reader] = manifest["contributions"]["readers"]
    assert "*" not in reader["filename_patterns"] and reader["accepts_directories"] is True
    assert set(reader["filename_patterns"]) == {"*.tif", "*.tiff", "acquisition.json", "*.zarr", "*.nd2", "*.czi", "*.lif"}


def test_predicted_images_open_as_a_stack_not_as_an_ri_volume(tmp_path) -> None:
    """``fdt forward --out`` writes images (axes TYX with the pixel size), which must not be taken for a volume."""
    from napari_fdt.data.io import write_stack_tiff

    data = _stack(np.float32)
    write_stack_tiff(tmp_path / "pred.tif", data, 0.33)
    head = probe_stack(tmp_path / "pred.tif")
    assert head is not None and not head.is_ri_like and head.optics == pytest.approx({"pixel_size_um": 0.33})
    [(back, kwargs, _)] = get_reader(str(tmp_path / "pred.tif"))(str(tmp_path / "pred.tif"))
    assert np.array_equal(stack_images(back), data) and kwargs["metadata"]["fdt_kind"] == "stack"


def test_bioio_reads_the_same_stack_and_optics_as_tifffile(tmp_path) -> None:
    """The bioio path (ND2, CZI, LIF in use) checked where both readers apply: OME-TIFF and ImageJ TIFF."""
    pytest.importorskip("bioio")
    pytest.importorskip("bioio_ome_tiff")
    pytest.importorskip("bioio_tifffile")
    from napari_fdt.data.microscope import read_with_bioio

    data = _ome_file(tmp_path / "cells.ome.tif")
    via_bioio, via_tifffile = read_with_bioio(tmp_path / "cells.ome.tif"), read_stack(tmp_path / "cells.ome.tif")
    assert np.array_equal(via_bioio.images, data) and via_bioio.optics == pytest.approx(via_tifffile.optics)
    assert via_bioio.optics["pixel_size_um"] == pytest.approx(0.325)  # the nm unit honoured (bioio's own sizes ignore it)
    tifffile.imwrite(tmp_path / "ij.tif", data, imagej=True, resolution=(1 / 0.45, 1 / 0.45), metadata={"unit": "micron", "axes": "TYX"})
    ij = read_with_bioio(tmp_path / "ij.tif")
    assert np.array_equal(ij.images, data) and ij.optics == pytest.approx({"pixel_size_um": 0.45})


def test_other_formats_are_declined_without_bioio_or_a_readable_file(tmp_path, monkeypatch) -> None:
    import napari_fdt.data.microscope as microscope

    (tmp_path / "scan.nd2").write_bytes(b"not an nd2 file")
    assert get_reader(str(tmp_path / "scan.nd2")) is None  # unreadable (or bioio absent)
    monkeypatch.setattr(microscope, "has_bioio", lambda: False)
    assert get_reader(str(tmp_path / "scan.nd2")) is None
    with pytest.raises(FDTInputError, match=r'^images: scan.nd2 needs bioio .*napari-fdt\[formats\]'):
        read_stack(tmp_path / "scan.nd2")
