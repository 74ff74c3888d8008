"""napari writer: an RI volume layer → OME-TIFF (or OME-Zarr) with its voxel size (µm), plus its report when the layer holds one.

The files are those of ``fdt reconstruct --out RI.tif``: float32 (Z, Y, X) absolute RI with the voxel size from
the layer's scale, and the report (``metadata["fdt_report"]``) beside it, named from the volume's full name
(``RI_lr0.05.ome.tif`` → ``RI_lr0.05.json``). A name ending in ``.zarr`` is written as OME-Zarr (NGFF 0.4), a
name without a volume ending gets ``.ome.tif``.

Only RI layers are written: a reconstruction or ground truth (``metadata["fdt_kind"]`` ``"ri"`` / ``"truth"``)
or a 3-D layer carrying a napari-fdt report. An image stack is refused with a message saying what to do
instead, before anything is written. Nothing user-made is replaced silently: napari's save dialog has asked
before replacing the volume itself, and the report is never written over the report of another volume
(``RI.tif`` and ``RI.ome.tif`` share ``RI.json``) nor left stale beside a replaced volume.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from napari_fdt.data.io import VOLUME_SUFFIXES, report_path  # re-exported: the writer puts the report where write_result does
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.napari.layers import META_KIND, META_REPORT

__all__ = ["write_ri", "report_path", "RI_KINDS"]

#: ``fdt_kind`` values of layers holding an absolute RI volume.
RI_KINDS = ("ri", "truth")


def _check_ri_layer(volume: np.ndarray, meta: dict[str, Any]) -> dict | None:
    """Refuse a layer that is not an RI volume; return its report (or None)."""
    name = meta.get("name", "the layer")
    md = meta.get("metadata") or {}
    report = md.get(META_REPORT)
    if not (isinstance(report, dict) and report.get("format") == "napari-fdt-report"):
        report = None
    if volume.ndim != 3:
        raise FDTInputError("layer", f"{name} is {volume.ndim}-D, not an RI volume (Z, Y, X)",
                            "save a 3-D RI layer, or use napari's own TIFF writer for other layers")
    kind = md.get(META_KIND)
    if kind not in RI_KINDS and report is None:
        what = {"acquisition": "an acquisition's image stack", "stack": "an image stack"}.get(kind, "not a napari-fdt RI volume")
        raise FDTInputError("layer", f"{name} is {what}, not an RI volume",
                            "select a reconstruction (or ground-truth) RI layer; save image stacks with napari's own "
                            "TIFF writer, or as an acquisition folder from the FDT acquisition widget")
    return report


def write_ri(path: str, data: Any, meta: dict[str, Any]) -> list[str]:
    """Write one RI layer (and its report); return the paths written.

    A refusal raises :class:`FDTInputError` before anything is written, and is also issued as an
    :class:`FDTWarning`: napari swallows a writer's ``ValueError`` when it looks for a writer itself
    (``layers.save(path, plugin=...)``) and reports only the warnings it recorded.
    """
    try:
        return _write_ri(path, data, meta)
    except FDTInputError as exc:
        warnings.warn(f"napari-fdt writer: {exc}", FDTWarning, stacklevel=2)
        raise


def _write_ri(path: str, data: Any, meta: dict[str, Any]) -> list[str]:
    from napari_fdt.data.io import check_report_free, write_json_atomic
    from napari_fdt.data.volumes import write_volume

    volume = np.asarray(data)
    report = _check_ri_layer(volume, meta)
    out = Path(path)
    if not out.name.lower().endswith(VOLUME_SUFFIXES):
        out = out.with_name(out.name + ".ome.tif")
    side = report_path(out)
    check_report_free(out)
    if report is None and side.exists():
        raise FDTInputError("out", f"{side.name} beside {out.name} is the report of the volume this save replaces, and this layer "
                            "has no report to put in its place", "choose another name, or move the old volume and its report first")
    scale = tuple(float(s) for s in (meta.get("scale") or (1.0, 1.0, 1.0)))[-3:]
    write_volume(out, volume.astype(np.float32), scale, overwrite=True)
    written = [str(out)]
    if report is not None:
        report = {**report, "output": str(out)}
        written.append(str(write_json_atomic(side, report, overwrite=True)))
    return written
