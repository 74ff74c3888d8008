"""Tests of the RI volume's OME-TIFF reader and writer (voxel size, units, overwrite rules, bad input); the acquisition
folder's are in test_io.py."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import tifffile

from napari_fdt.data.io import read_volume_tiff, write_volume_tiff
from napari_fdt.errors import FDTInputError


@pytest.mark.parametrize("shape", [(5, 9, 11), (1, 8, 10)])
def test_volume_round_trip(tmp_path: Path, shape: tuple[int, int, int]) -> None:
    vol = np.random.default_rng(3).normal(1.33, 0.01, size=shape).astype(np.float32)
    target = tmp_path / "out" / "ri.ome.tif"
    assert write_volume_tiff(target, vol, (2.0, 0.5, 0.25)) == target
    with tifffile.TiffFile(target) as tif:
        assert tif.is_ome
        assert 'PhysicalSizeZUnit="µm"' in tif.ome_metadata
    back, voxel = read_volume_tiff(target)
    assert back.dtype == np.float32 and back.shape == shape
    np.testing.assert_array_equal(back, vol)
    assert voxel == (2.0, 0.5, 0.25)
    assert sorted(p.name for p in target.parent.iterdir()) == ["ri.ome.tif"]


def test_volume_overwrite_rules(tmp_path: Path) -> None:
    target = tmp_path / "ri.tif"  # not named .ome.tif: still written as OME
    write_volume_tiff(target, np.ones((2, 8, 8)), (1.0, 1.0, 1.0))
    with tifffile.TiffFile(target) as tif:
        assert tif.is_ome
    before = target.read_bytes()
    with pytest.raises(FDTInputError) as err:
        write_volume_tiff(target, np.zeros((2, 8, 8), np.float32), (1.0, 1.0, 1.0))
    assert err.value.field == "path"
    assert target.read_bytes() == before
    write_volume_tiff(target, np.zeros((3, 8, 8), np.float32), (3.0, 0.3, 0.3), overwrite=True)
    vol, voxel = read_volume_tiff(target)
    assert vol.shape == (3, 8, 8) and not vol.any()
    assert voxel == pytest.approx((3.0, 0.3, 0.3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ri.tif"]


def test_write_volume_rejects_bad_input(tmp_path: Path) -> None:
    vol = np.ones((2, 8, 8), np.float32)
    for bad_vol in (np.ones((8, 8), np.float32), np.ones((2, 8, 8), np.complex64)):
        with pytest.raises(FDTInputError) as err:
            write_volume_tiff(tmp_path / "v.tif", bad_vol, (1.0, 1.0, 1.0))
        assert err.value.field == "volume"
    vol_nan = vol.copy()
    vol_nan[1, 2, 3] = np.nan
    with pytest.raises(FDTInputError, match="z=1, y=2, x=3") as err:
        write_volume_tiff(tmp_path / "v.tif", vol_nan, (1.0, 1.0, 1.0))
    assert err.value.field == "volume"
    for voxel in ((1.0, 1.0), (1.0, 0.0, 1.0), (1.0, -1.0, 1.0), (1.0, math.nan, 1.0)):
        with pytest.raises(FDTInputError) as err:
            write_volume_tiff(tmp_path / "v.tif", vol, voxel)  # type: ignore[arg-type]
        assert err.value.field == "voxel_size_um"
    assert list(tmp_path.iterdir()) == []


def test_read_volume_errors(tmp_path: Path) -> None:
    def field_of(path: Path) -> str:
        with pytest.raises(FDTInputError) as err:
            read_volume_tiff(path)
        return err.value.field

    assert field_of(tmp_path / "absent.tif") == "absent.tif"
    (tmp_path / "text.tif").write_text("no tiff here")
    assert field_of(tmp_path / "text.tif") == "text.tif"
    tifffile.imwrite(tmp_path / "flat.tif", np.ones((8, 8), np.float32))
    assert field_of(tmp_path / "flat.tif") == "flat.tif"
    tifffile.imwrite(tmp_path / "nan.tif", np.full((2, 8, 8), np.nan, np.float32))
    assert field_of(tmp_path / "nan.tif") == "nan.tif"
    write_volume_tiff(tmp_path / "cut.ome.tif", np.ones((4, 32, 32)), (1.0, 1.0, 1.0))
    data = (tmp_path / "cut.ome.tif").read_bytes()
    (tmp_path / "cut.ome.tif").write_bytes(data[: len(data) // 2])
    assert field_of(tmp_path / "cut.ome.tif") == "cut.ome.tif"


def test_read_plain_tiff_volume_has_no_voxel_size(tmp_path: Path) -> None:
    vol = np.arange(2 * 8 * 9, dtype=np.float32).reshape(2, 8, 9)
    tifffile.imwrite(tmp_path / "plain.tif", vol, photometric="minisblack")
    back, voxel = read_volume_tiff(tmp_path / "plain.tif")
    np.testing.assert_array_equal(back, vol)
    assert voxel is None


def test_read_volume_converts_ome_units(tmp_path: Path) -> None:
    vol = np.ones((2, 8, 8), np.float32)
    meta = {"axes": "ZYX", "PhysicalSizeZ": 2000.0, "PhysicalSizeZUnit": "nm",
            "PhysicalSizeY": 0.5, "PhysicalSizeX": 0.25}  # Y, X: OME's default unit µm
    tifffile.imwrite(tmp_path / "v.ome.tif", vol, ome=True, metadata=meta)
    assert read_volume_tiff(tmp_path / "v.ome.tif")[1] == pytest.approx((2.0, 0.5, 0.25))


def test_a_full_disk_during_a_save_keeps_the_previous_volume(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A write that fails half-way (a mocked full disk) leaves the previous RI volume byte-identical, no temporary file,
    and a clear error naming the path and the fix (issue 28, item 4)."""
    import errno

    from napari_fdt.data import io as fdt_io

    path = write_volume_tiff(tmp_path / "RI.tif", np.full((2, 4, 5), 1.33, np.float32), (2.0, 0.3, 0.3))
    before = path.read_bytes()

    def full_disk(file, *args, **kwargs) -> None:
        Path(file).write_bytes(b"half a volume")  # what a write cut short leaves
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(fdt_io.tifffile, "imwrite", full_disk)
    with pytest.raises(FDTInputError, match=r"^path: could not write .*RI.tif: No space left on device \(the previous one is "
                                            r"unchanged\) \(free space on that disk or choose a writable location\)"):
        write_volume_tiff(path, np.full((2, 4, 5), 1.4, np.float32), (2.0, 0.3, 0.3), overwrite=True)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["RI.tif"]
