"""napari reader: acquisition folders, napari-fdt RI volumes, and bare TIFF stacks.

``get_reader(path)`` returns None for paths that are not ours (napari then tries other readers) and a
reader function otherwise. Problems inside something that is ours (a broken ``acquisition.json``, an
unreadable TIFF) are raised as the core's :class:`~napari_fdt.errors.FDTInputError`, whose one-line
message (``field: problem (fix)``) napari shows to the user.

* An acquisition folder (or its ``acquisition.json``) → one image layer of the stack (N, H, W), scale
  (1, dx, dx) µm, the :class:`~napari_fdt.data.acquisition.Acquisition` in ``metadata["fdt_acquisition"]``.
* An RI volume written by napari-fdt (an OME-TIFF with a ``napari-fdt-report`` JSON beside it, or with
  a z voxel size) → an image layer with the volume's physical scale; the report in ``metadata["fdt_report"]``.
* Any other TIFF of shape (N, H, W) or (H, W) → an image layer flagged ``fdt_needs_optics``: the
  acquisition widget asks for the optics.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

import numpy as np

from napari_fdt.errors import FDTInputError
from napari_fdt.napari.layers import META_REPORT, UNITS, LayerDataTuple, acquisition_layer, stack_layer

__all__ = ["get_reader", "read_acquisition_layers", "read_tiff_layers"]

_TIFF_SUFFIXES = (".tif", ".tiff")


def _single(path: str | list[str]) -> str | None:
    if isinstance(path, (list, tuple)):
        return str(path[0]) if len(path) == 1 else None
    return str(path)


def get_reader(path: str | list[str]) -> Callable[[str | list[str]], list[LayerDataTuple]] | None:
    """The reader for ``path`` if it is an acquisition folder, its ``acquisition.json`` or a TIFF, else None."""
    p = _single(path)
    if p is None:
        return None
    q = Path(p)
    if q.is_dir():
        return read_acquisition_layers if (q / "acquisition.json").is_file() else None
    if q.name == "acquisition.json" and q.is_file():
        return read_acquisition_layers
    if q.suffix.lower() in _TIFF_SUFFIXES and q.is_file():
        return read_tiff_layers
    return None


def read_acquisition_layers(path: str | list[str]) -> list[LayerDataTuple]:
    """An acquisition folder → ``[image layer]``; raises :class:`FDTInputError` with the core's message."""
    from napari_fdt.data.io import read_acquisition

    p = Path(_single(path))
    acq = read_acquisition(p)
    folder = p if p.is_dir() else p.parent
    return [acquisition_layer(acq, path=str(folder), name=folder.name or "acquisition")]


def _report_beside(tif: Path) -> dict[str, Any] | None:
    from napari_fdt.data.io import report_path

    side = report_path(tif)
    if not side.is_file():
        return None
    try:
        data = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("format") == "napari-fdt-report" else None


def read_tiff_layers(path: str | list[str]) -> list[LayerDataTuple]:
    """A TIFF → an RI volume layer (napari-fdt OME-TIFF) or a stack layer that needs optics."""
    import tifffile

    from napari_fdt.data.io import _quiet_tifffile, read_image_stack, read_volume_tiff

    p = Path(_single(path))
    report = _report_beside(p)
    try:
        with _quiet_tifffile(), tifffile.TiffFile(p) as tif:
            ome_z = tif.is_ome and "PhysicalSizeZ" in (tif.ome_metadata or "")
    except Exception as exc:  # tifffile raises many kinds on corrupt files
        raise FDTInputError("images", f"{p.name} is not a readable TIFF: {exc}", "re-export it as a grayscale TIFF stack") from exc
    if report is not None or ome_z:
        volume, voxel = read_volume_tiff(p)
        meta: dict[str, Any] = {"fdt_kind": "ri", "fdt_path": str(p)}
        if report is not None:
            meta[META_REPORT] = report
            voxel = voxel or tuple(report.get("ri", {}).get("voxel_size_um", ())) or None
        kwargs: dict[str, Any] = dict(name=p.name.split(".")[0], metadata=meta, units=UNITS, colormap="magma")
        if voxel:
            dz, dy, dx = (float(v) for v in voxel)
            h, w = volume.shape[1:]
            kwargs.update(scale=(dz, dy, dx), translate=(0.5 * dz, -(h // 2) * dy, -(w // 2) * dx))
        return [(volume, kwargs, "image")]
    images = read_image_stack(p, p.name)  # layout, pixel type and memory checked from the header first
    if images.ndim == 2:
        images = images[None]
    if images.dtype.kind == "f" and not np.isfinite(images).all():
        raise FDTInputError("images", f"{p.name} holds NaN or Inf pixels", "replace or mask the bad pixels first")
    return [stack_layer(images, path=str(p), name=p.stem)]
