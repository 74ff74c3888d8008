"""napari writer: an RI volume layer → OME-TIFF with its voxel size (µm), plus ``RI.json`` when the layer holds a report.

The files are those of ``fdt reconstruct --out RI.tif``: float32 (Z, Y, X) absolute RI with
``PhysicalSizeZ/Y/X`` from the layer's scale, and the report (``metadata["fdt_report"]``) beside it,
named like the volume with ``.json`` (``RI.tif`` → ``RI.json``). Both are written atomically; napari's
save dialog has already asked before replacing a file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from napari_fdt.data.io import report_path  # re-exported: the writer puts the report where write_result does
from napari_fdt.errors import FDTInputError
from napari_fdt.napari.layers import META_REPORT

__all__ = ["write_ri", "report_path"]


def write_ri(path: str, data: Any, meta: dict[str, Any]) -> list[str]:
    """Write one 3-D image layer; return the paths written."""
    from napari_fdt.data.io import write_json_atomic, write_volume_tiff

    volume = np.asarray(data)
    if volume.ndim != 3:
        raise FDTInputError("layer", f"{meta.get('name', 'the layer')} is {volume.ndim}-D, not an RI volume (Z, Y, X)",
                            "save a 3-D RI layer, or use napari's own TIFF writer for other layers")
    out = Path(path)
    if out.suffix.lower() not in (".tif", ".tiff"):
        out = out.with_name(out.name + ".ome.tif")
    scale = tuple(float(s) for s in (meta.get("scale") or (1.0, 1.0, 1.0)))[-3:]
    write_volume_tiff(out, volume.astype(np.float32), scale, overwrite=True)
    written = [str(out)]
    report = (meta.get("metadata") or {}).get(META_REPORT)
    if report is not None:
        report = {**report, "output": str(out)}
        written.append(str(write_json_atomic(report_path(out), report, overwrite=True)))
    return written
