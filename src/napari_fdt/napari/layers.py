"""Layer data for napari, built without importing napari or Qt: physical scale, placement, units, metadata.

The plugin's coordinate convention (``docs/napari.md``): napari's world coordinates are the acquisition's
physical coordinates in µm, axes (z, y, x).

* x, y are measured from the image centre (``docs/format.md``): pixel (i, j) of an H×W image sits at
  ``y = (i − H//2)·dx``, ``x = (j − W//2)·dx``.
* z runs along the optical axis (light travels +z) with the volume's **bottom face at z = 0** and its top
  face at ``z = T = n_slices·dz``. Voxel (k, i, j) of an RI volume has its centre at ``z = (k + ½)·dz``.
* A source ``[x, y, depth]`` sits at ``z = −depth``: its point is ``(−depth, y, x)``.
* Image stacks (N, H, W) are shown as (N, 1, H, W): axis 0 is the **image index**, an axis of its own (label
  ``image``, unit pixel), so a stack and an RI volume never share a slider; axis 1 is a single plane spanning
  the volume's z range (0 … T), so the image shows at every z of the volume in 2D. Same lateral placement.

A layer data tuple is ``(data, kwargs, layer_type)``, what napari readers and sample-data functions return.
"""

from __future__ import annotations

import uuid
from typing import Any

import numpy as np

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTInputError
from napari_fdt.physics.optics import Optics

__all__ = [
    "UNITS",
    "META_ACQUISITION", "META_PATH", "META_NEEDS_OPTICS", "META_ID", "META_KIND", "META_OWNER", "META_REPORT",
    "lateral_translate", "volume_scale", "volume_translate", "stack_scale", "stack_translate",
    "sources_to_points", "points_to_sources", "acquisition_layer", "stack_layer", "ri_layer", "sources_layer",
    "side_by_side", "new_id", "META_FILE_OPTICS", "META_OPTICS_ENTRIES", "STACK_AXIS_LABELS", "STACK_UNITS",
    "stack_view", "stack_images", "source_point_size_um",
]

#: Units of every axis of every layer the plugin makes (napari needs them consistent across layers).
UNITS = ("µm", "µm", "µm")

#: Layer metadata keys. ``fdt_acquisition``: the :class:`Acquisition` of an image stack; ``fdt_path``: where it
#: was read from; ``fdt_needs_optics``: a bare TIFF stack waiting for its optics; ``fdt_id``: a stable id of the
#: acquisition layer; ``fdt_kind``: what the layer holds (``acquisition``, ``stack``, ``ri`` (a reconstruction),
#: ``truth`` (a ground-truth RI), ``sources``, ``masks``, ``preview``, ``coverage``, ``comparison``); ``fdt_owner``: the ``fdt_id`` of the acquisition a derived layer
#: belongs to; ``fdt_report``: the reconstruction report (content of ``RI.json``); ``fdt_file_optics``: the optics
#: fields a microscope file states (``napari_fdt.data.microscope``: a dict holding only the fields found, µm).
META_ACQUISITION = "fdt_acquisition"
META_PATH = "fdt_path"
META_NEEDS_OPTICS = "fdt_needs_optics"
META_ID = "fdt_id"
META_KIND = "fdt_kind"
META_OWNER = "fdt_owner"
META_REPORT = "fdt_report"
#: Optics a reader found in a file (Optics field name → value; absent fields missing), used to prefill the widget.
META_FILE_OPTICS = "fdt_file_optics"
#: Optics as typed in the acquisition widget for this layer (field → text), kept per layer.
META_OPTICS_ENTRIES = "fdt_optics_entries"

#: Axes of a stack layer (N, 1, H, W): the image index has its own axis and unit.
STACK_AXIS_LABELS = ("image", "z", "y", "x")
STACK_UNITS = ("pixel", "µm", "µm", "µm")

LayerDataTuple = tuple[Any, dict[str, Any], str]


def new_id() -> str:
    """A fresh id for an acquisition layer."""
    return uuid.uuid4().hex


def lateral_translate(image_shape: tuple[int, int], pixel_size_um: float) -> tuple[float, float]:
    """(y, x) world position of pixel (0, 0), µm: ``−(H//2)·dx, −(W//2)·dx``."""
    h, w = image_shape
    return -(h // 2) * float(pixel_size_um), -(w // 2) * float(pixel_size_um)


def volume_scale(optics: Optics) -> tuple[float, float, float]:
    """(dz, dx, dx) of an RI volume, µm."""
    return float(optics.slice_spacing_um), float(optics.pixel_size_um), float(optics.pixel_size_um)


def volume_translate(optics: Optics, image_shape: tuple[int, int]) -> tuple[float, float, float]:
    """World position of voxel (0, 0, 0)'s centre: ``(dz/2, −(H//2)·dx, −(W//2)·dx)`` µm."""
    return (0.5 * float(optics.slice_spacing_um), *lateral_translate(image_shape, optics.pixel_size_um))


def stack_scale(pixel_size_um: float, thickness_um: float = 1.0) -> tuple[float, float, float, float]:
    """(1, T, dx, dx) of a stack layer (N, 1, H, W): axis 0 the image index, axis 1 one plane as thick as the volume."""
    return 1.0, float(thickness_um), float(pixel_size_um), float(pixel_size_um)


def stack_translate(image_shape: tuple[int, int], pixel_size_um: float,
                    thickness_um: float = 1.0) -> tuple[float, float, float, float]:
    """(0, T/2, −(H//2)·dx, −(W//2)·dx) µm: the plane's centre mid-volume, so it spans z = 0 … T."""
    return (0.0, 0.5 * float(thickness_um), *lateral_translate(image_shape, pixel_size_um))


def stack_view(images: np.ndarray) -> np.ndarray:
    """(N, H, W) → (N, 1, H, W), a view (no copy): the layer data of a stack."""
    a = np.asarray(images) if not hasattr(images, "ndim") else images
    return a[:, None] if a.ndim == 3 else a


def stack_images(data: Any) -> np.ndarray:
    """The (N, H, W) images of a stack layer's data: (N, 1, H, W) or (N, H, W); a 2-D image → (1, H, W)."""
    a = np.asarray(data)
    if a.ndim == 4 and a.shape[1] == 1:
        return a[:, 0]
    if a.ndim == 2:
        return a[None]
    return a


def source_point_size_um(image_shape: tuple[int, int], pixel_size_um: float) -> float:
    """A source point's size: 3 % of the field of view (at least 3 pixels), visible in 2D and 3D."""
    return max(3.0 * float(pixel_size_um), 0.03 * max(image_shape) * float(pixel_size_um))


def sources_to_points(sources_um: np.ndarray) -> np.ndarray:
    """Sources (N, 3) ``[x, y, depth]`` µm → napari points (N, 3) ``(z, y, x) = (−depth, y, x)`` µm."""
    s = np.asarray(sources_um, dtype=np.float64).reshape(-1, 3)
    return np.column_stack([-s[:, 2], s[:, 1], s[:, 0]])


def points_to_sources(points: np.ndarray, n_images: int | None = None) -> np.ndarray:
    """Napari points (N, 3) ``(z, y, x)`` µm → sources (N, 3) ``[x, y, depth = −z]``, checked.

    Raises :class:`FDTInputError` for a wrong count (``n_images``) or a point not below the volume (z ≥ 0).
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise FDTInputError("sources", f"the points layer must hold 3-D points (z, y, x), got shape {p.shape}",
                            "fit the sources again to rebuild the layer")
    if n_images is not None and p.shape[0] != n_images:
        raise FDTInputError("sources", f"the points layer holds {p.shape[0]} points for {n_images} images",
                            "keep exactly one point per image (fit the sources again to start over)")
    above = np.flatnonzero(~(p[:, 0] < 0))
    if above.size:
        i = int(above[0])
        raise FDTInputError(f"sources[{i}]", f"point at z = {p[i, 0]:g} µm is not below the volume's bottom face (z = 0)",
                            "sources lie below the volume: move the point to z < 0 (z = −depth)")
    if not np.isfinite(p).all():
        raise FDTInputError("sources", "a point has a non-finite coordinate", "fit the sources again")
    return np.column_stack([p[:, 2], p[:, 1], -p[:, 0]])


def acquisition_layer(acq: Acquisition, path: str | None = None, name: str | None = None) -> LayerDataTuple:
    """Image layer of an acquisition's stack (N, H, W): scale (1, dx, dx), units µm, the acquisition in metadata."""
    o = acq.optics
    meta = {META_ACQUISITION: acq, META_PATH: path, META_ID: new_id(), META_KIND: "acquisition"}
    kwargs = dict(name=name or "acquisition", scale=stack_scale(o.pixel_size_um, o.thickness_um),
                  translate=stack_translate(acq.image_shape, o.pixel_size_um, o.thickness_um), units=STACK_UNITS,
                  axis_labels=STACK_AXIS_LABELS, metadata=meta, colormap="gray")
    return stack_view(acq.images), kwargs, "image"


def stack_layer(images: np.ndarray, path: str | None = None, name: str | None = None,
                file_optics: dict[str, float] | None = None) -> LayerDataTuple:
    """Image layer of a bare stack (N, H, W) without complete optics: flagged ``fdt_needs_optics``.

    ``file_optics``: the optics fields the file states (``META_FILE_OPTICS``); with its ``pixel_size_um`` the
    layer gets its lateral scale (µm) and the image-centred placement. Without it the lateral axes are in pixels
    (scale 1, unit pixel) until the optics are applied, so the scale bar does not claim micrometres it does not know.
    """
    meta: dict[str, Any] = {META_NEEDS_OPTICS: True, META_PATH: path, META_ID: new_id(), META_KIND: "stack"}
    kwargs: dict[str, Any] = dict(name=name or "stack", scale=(1.0, 1.0, 1.0, 1.0), units=("pixel",) * 4,
                                  axis_labels=STACK_AXIS_LABELS, metadata=meta, colormap="gray")
    if file_optics is not None:
        meta[META_FILE_OPTICS] = dict(file_optics)
        dx = file_optics.get("pixel_size_um")
        if dx:
            kwargs.update(scale=stack_scale(dx), translate=stack_translate(np.shape(images)[-2:], dx), units=STACK_UNITS)
    return stack_view(images), kwargs, "image"


def ri_layer(ri: np.ndarray, optics: Optics, name: str, owner: str | None = None,
             report: dict | None = None) -> LayerDataTuple:
    """Image layer of an absolute RI volume (n_slices, H, W): scale (dz, dx, dx), voxel centres placed in µm."""
    meta: dict[str, Any] = {META_KIND: "ri", META_OWNER: owner}
    if report is not None:
        meta[META_REPORT] = report
    ri = np.asarray(ri, dtype=np.float32)
    kwargs = dict(name=name, scale=volume_scale(optics), translate=volume_translate(optics, ri.shape[1:]),
                  units=UNITS, metadata=meta, colormap="magma")
    return ri, kwargs, "image"


def sources_layer(sources_um: np.ndarray, name: str, owner: str | None, size_um: float = 1.0,
                  kind: str = "sources", colour: str = "cyan") -> LayerDataTuple:
    """Points layer of the sources at ``(−depth, y, x)`` µm: ``kind`` ``sources`` (the editable start of a run) or
    ``calibrated`` (a run's result). Drawn at every z (``projection_mode="all"``) so they show over the images in 2D."""
    meta = {META_KIND: kind, META_OWNER: owner}
    kwargs = dict(name=name, ndim=3, size=size_um, face_color=colour, units=UNITS, metadata=meta,
                  projection_mode="all")
    return sources_to_points(sources_um), kwargs, "points"


def side_by_side(predicted: np.ndarray, measured: np.ndarray, gap_px: int = 2) -> np.ndarray:
    """(H, 2W + gap) image: predicted on the left, measured on the right, the gap at the images' minimum."""
    p = np.asarray(predicted, dtype=np.float32)
    m = np.asarray(measured, dtype=np.float32)
    if p.shape != m.shape or p.ndim != 2:
        raise ValueError(f"need two images of one shape, got {p.shape} and {m.shape}")
    fill = float(min(p.min(), m.min()))
    gap = np.full((p.shape[0], gap_px), fill, dtype=np.float32)
    return np.concatenate([p, gap, m], axis=1)
