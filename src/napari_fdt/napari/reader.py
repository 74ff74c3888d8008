"""napari reader: acquisition folders, napari-fdt RI volumes (OME-TIFF, OME-Zarr), microscope stacks, per-source files.

``get_reader(path)`` decides from names and file headers alone (no pixels read) and returns None for what this
plugin cannot read, so that napari offers the file to other readers; it returns a reader function otherwise.
Problems inside something it accepted (a broken ``acquisition.json``, a truncated TIFF) are raised as the
core's :class:`~napari_fdt.errors.FDTInputError`, whose one-line message (``field: problem (fix)``) napari shows.

* An acquisition folder (or its ``acquisition.json``) → one image layer of the stack (N, H, W), scale
  (1, dx, dx) µm, the :class:`~napari_fdt.data.acquisition.Acquisition` in ``metadata["fdt_acquisition"]``.
* An RI volume: an OME-TIFF with its napari-fdt report beside it, a float OME-TIFF volume (axes ZYX with a z
  voxel size), or an OME-Zarr folder written by napari-fdt → an image layer with the volume's physical
  scale and placement; the report (if any) in ``metadata["fdt_report"]``.
* A microscope TIFF stack (OME-TIFF, ImageJ or plain; one axis besides Y and X), a folder of 2-D TIFFs or a
  list of them (one image per source) → a stack layer flagged ``fdt_needs_optics``, with the optics fields the
  file states in ``metadata["fdt_file_optics"]`` (:mod:`napari_fdt.data.microscope`) and, where the pixel size
  is known, the lateral scale.
"""

from __future__ import annotations

import json
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np

from napari_fdt.data.mapped import chunks
from napari_fdt.errors import FDTInputError
from napari_fdt.napari.layers import META_KIND, META_PATH, META_REPORT, UNITS, LayerDataTuple, acquisition_layer, stack_layer

__all__ = ["get_reader", "read_acquisition_layers", "read_tiff_layers", "read_source_layers", "read_zarr_layers"]

Reader = Callable[[Any], list[LayerDataTuple]]


def _paths(path: str | list[str]) -> list[str]:
    return [str(p) for p in path] if isinstance(path, (list, tuple)) else [str(path)]


def get_reader(path: str | list[str]) -> Reader | None:
    """The reader for ``path`` if this plugin reads it (decided from names and headers), else None."""
    from napari_fdt.data.microscope import list_source_files, probe_source_files, probe_stack
    from napari_fdt.data.ome_zarr import has_zarr, is_ome_zarr

    paths = _paths(path)
    if not paths:
        return None
    if len(paths) > 1:  # several files: one image per source
        return partial(_read_sources, paths) if probe_source_files(paths) else None
    q = Path(paths[0])
    if q.is_dir():
        if (q / "acquisition.json").is_file():
            return read_acquisition_layers
        if is_ome_zarr(q):
            return read_zarr_layers if has_zarr() else None
        files = list_source_files(q)
        return partial(_read_sources, q) if files and probe_source_files(files) else None
    if q.name == "acquisition.json" and q.is_file():
        return read_acquisition_layers
    head = probe_stack(q)
    return None if head is None else read_tiff_layers


def read_acquisition_layers(path: str | list[str]) -> list[LayerDataTuple]:
    """An acquisition folder → ``[image layer]``; raises :class:`FDTInputError` with the core's message."""
    from napari_fdt.data.io import read_acquisition

    p = Path(_paths(path)[0])
    acq = read_acquisition(p)
    folder = p if p.is_dir() else p.parent
    return [acquisition_layer(acq, path=str(folder), name=folder.name or "acquisition")]


def _report_beside(volume: Path) -> dict[str, Any] | None:
    """The napari-fdt report beside ``volume`` if it describes this file (its ``output`` names it), else None."""
    from napari_fdt.data.io import report_path

    side = report_path(volume)
    if not side.is_file():
        return None
    try:
        data = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("format") != "napari-fdt-report":
        return None
    output = data.get("output")
    if isinstance(output, str) and Path(output).name != volume.name:
        return None  # RI.json of RI.tif is not the report of RI.ome.tif
    return data


def _volume_name(p: Path) -> str:
    from napari_fdt.data.io import report_path

    return report_path(p).stem  # the full name less its volume ending: RI_lr0.05.tif → RI_lr0.05


def _ri_layer(volume: np.ndarray, voxel, translate, p: Path, report: dict | None) -> LayerDataTuple:
    meta: dict[str, Any] = {META_KIND: "ri", META_PATH: str(p)}
    if report is not None:
        meta[META_REPORT] = report
        voxel = voxel or tuple(report.get("ri", {}).get("voxel_size_um", ())) or None
    kwargs: dict[str, Any] = dict(name=_volume_name(p), metadata=meta, units=UNITS, colormap="magma")
    if voxel:
        dz, dy, dx = (float(v) for v in voxel)
        h, w = volume.shape[1:]
        kwargs.update(scale=(dz, dy, dx), translate=translate or (0.5 * dz, -(h // 2) * dy, -(w // 2) * dx))
    return volume, kwargs, "image"


def read_tiff_layers(path: str | list[str]) -> list[LayerDataTuple]:
    """A TIFF → an RI volume layer (a napari-fdt volume) or a microscope stack layer with the file's optics."""
    from napari_fdt.data.io import read_volume_tiff
    from napari_fdt.data.microscope import probe_stack, read_stack

    p = Path(_paths(path)[0])
    head = probe_stack(p)
    report = _report_beside(p)
    if report is not None or (head is not None and head.is_ri_like):
        volume, voxel = read_volume_tiff(p)
        return [_ri_layer(volume, voxel, None, p, report)]
    stack = read_stack(p)  # raises the reason when the header does not describe a stack
    return [_stack(stack, str(p), _volume_name(p))]


def _stack(stack, path: str, name: str) -> LayerDataTuple:
    images = stack.images
    if images.dtype.kind == "f" and not all(np.isfinite(images[s]).all() for s in chunks(images)):
        raise FDTInputError("images", f"{name} holds NaN or Inf pixels", "replace or mask the bad pixels first")
    return stack_layer(images, path=path, name=name, file_optics=stack.optics)


def _read_sources(paths: str | Path | list[str], _path: Any = None) -> list[LayerDataTuple]:
    from napari_fdt.data.microscope import read_source_files

    stack = read_source_files(paths)
    if isinstance(paths, (str, Path)):
        where, name = str(paths), Path(paths).name or "sources"
    else:
        where, name = str(Path(paths[0]).parent), f"{Path(paths[0]).parent.name or 'sources'} ({len(paths)} files)"
    return [_stack(stack, where, name)]


def read_source_layers(path: str | list[str]) -> list[LayerDataTuple]:
    """A folder of 2-D TIFFs (natural name order) or a list of them → one stack layer, one image per file."""
    paths = _paths(path)
    return _read_sources(paths[0] if len(paths) == 1 and Path(paths[0]).is_dir() else paths)


def read_zarr_layers(path: str | list[str]) -> list[LayerDataTuple]:
    """An OME-Zarr RI volume written by napari-fdt → an image layer with its scale and translation."""
    from napari_fdt.data.ome_zarr import read_volume_zarr

    p = Path(_paths(path)[0])
    volume, voxel, translate = read_volume_zarr(p)
    return [_ri_layer(volume, voxel, translate, p, _report_beside(p))]
