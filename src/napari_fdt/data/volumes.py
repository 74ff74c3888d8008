"""RI volumes on disk in either format, chosen by the name's ending: OME-TIFF (``.tif``, ``.ome.tif``) or
OME-Zarr (``.zarr``, ``.ome.zarr``, needs the optional zarr package). Voxel sizes ``(dz, dy, dx)`` in µm."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from napari_fdt.data.io import PathLike, read_volume_tiff, write_volume_tiff
from napari_fdt.data.ome_zarr import ZARR_SUFFIXES, read_volume_zarr, write_volume_zarr

__all__ = ["is_zarr_name", "write_volume", "read_volume"]


def is_zarr_name(path: PathLike) -> bool:
    """Whether the name ends in ``.zarr`` (``.ome.zarr`` included), case-insensitively."""
    return Path(path).name.lower().endswith(ZARR_SUFFIXES)


def write_volume(path: PathLike, volume: np.ndarray, voxel_size_um: tuple[float, float, float], *, overwrite: bool = False) -> Path:
    """Write a ``(Z, Y, X)`` RI volume as OME-Zarr when the name ends in ``.zarr``, else as OME-TIFF; atomically."""
    if is_zarr_name(path):
        return write_volume_zarr(path, volume, voxel_size_um, overwrite=overwrite)
    return write_volume_tiff(path, volume, voxel_size_um, overwrite=overwrite)


def read_volume(path: PathLike) -> tuple[np.ndarray, tuple[float, float, float] | None]:
    """``(volume float32 (Z, Y, X), voxel size (dz, dy, dx) µm or None)`` from an OME-Zarr folder or a TIFF."""
    p = Path(path)
    if p.is_dir() and is_zarr_name(p):
        vol, voxel, _ = read_volume_zarr(p)
        return vol, voxel
    return read_volume_tiff(p)
