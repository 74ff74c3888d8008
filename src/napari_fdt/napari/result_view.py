"""Putting a reconstruction in view: the RI layer selected, at a slice with content, contrast from the data, the
z slider kept inside the volume when the sources layer (which lies below the volume) appears, an oblique 3D camera,
and the key numbers of a run in one line. Public napari API only; no physics (the error against a truth is
:func:`napari_fdt.recon.assess.metrics.relative_delta_n_error`).

Axes: the RI volume (n_slices, H, W) is the viewer's last three dimensions (z, y, x), so its z is dims axis
``ndim − 3`` whatever the other layers (a stack layer adds the image axis in front).
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator

import numpy as np

from napari_fdt.napari.layers import META_ID, META_KIND, META_OWNER

__all__ = ["ri_contrast_limits", "CONTRAST_SAMPLE", "content_slice", "show_slice", "z_inside", "keep_view", "truth_layer",
           "truth_error", "results_line", "OBLIQUE_ANGLES", "oblique_camera", "camera", "STRUCTURE_DN", "show_bounds"]

#: napari camera angles (degrees) of the first 3D view: the volume seen from above and aside, so that slices do not
#: overlap into one block (napari's default, (0, 0, 90), looks straight down the z axis).
OBLIQUE_ANGLES = (-20.0, 35.0, 130.0)


#: Most voxels :func:`ri_contrast_limits` reads (an even stride through larger volumes): it runs in the GUI thread at
#: every update of a run: 64 ms on a 14×512×512 volume read whole, 9 ms with this sample (2 CPU cores).
CONTRAST_SAMPLE = 1 << 18


def ri_contrast_limits(ri: np.ndarray, n_background: float) -> tuple[float, float]:
    """Contrast limits of an absolute RI volume from its data: the 0.1 and 99.9 percentiles (of at most
    :data:`CONTRAST_SAMPLE` voxels, evenly strided), widened to hold the medium's index (so that the background is the
    colormap's low end or middle), never narrower than 1e-4."""
    flat = np.asarray(ri, dtype=np.float32).reshape(-1)
    sample = flat[:: max(1, flat.size // CONTRAST_SAMPLE)]
    finite = sample[np.isfinite(sample)]
    if finite.size == 0:
        return float(n_background), float(n_background) + 1e-4
    lo, hi = (float(v) for v in np.percentile(finite, (0.1, 99.9)))
    lo, hi = min(lo, float(n_background)), max(hi, float(n_background))
    return lo, max(hi, lo + 1e-4)


def content_slice(ri: np.ndarray, n_background: float) -> int:
    """The slice (index along axis 0) with the largest mean |RI − n_b|: where the structure is."""
    a = np.abs(np.asarray(ri, dtype=np.float32) - np.float32(n_background))
    a[~np.isfinite(a)] = 0
    return int(np.argmax(a.reshape(a.shape[0], -1).mean(axis=1)))


def _z_axis(viewer) -> int:
    return viewer.dims.ndim - 3


def _layer_z_range(layer) -> tuple[float, float]:
    """World z of the layer's first and last slice centres, µm."""
    z0, dz, n = float(layer.translate[0]), float(layer.scale[0]), int(layer.data.shape[0])
    return z0, z0 + (n - 1) * dz


def show_slice(viewer, layer, index: int) -> None:
    """Move the z slider to slice ``index`` of the RI ``layer`` (world coordinates, µm)."""
    if viewer.dims.ndim < 3:
        return
    viewer.dims.set_point(_z_axis(viewer), float(layer.translate[0]) + int(index) * float(layer.scale[0]))


def z_inside(viewer, layer) -> bool:
    """Whether the z slider stands within the RI ``layer``'s slices (half a slice of margin)."""
    if viewer.dims.ndim < 3:
        return True
    z = float(viewer.dims.point[_z_axis(viewer)])
    lo, hi = _layer_z_range(layer)
    half = 0.5 * abs(float(layer.scale[0]))
    return lo - half <= z <= hi + half


@contextmanager
def keep_view(viewer) -> Iterator[None]:
    """Add or update layers without moving the view: the selected layer and the z slider's position stay.

    A new layer becomes the selected one and may widen the z range (calibrated sources lie below the volume),
    which moves the slider; both are put back on leaving."""
    active = viewer.layers.selection.active
    point = tuple(viewer.dims.point)
    ndim = viewer.dims.ndim
    yield
    if active is not None and active in viewer.layers and viewer.layers.selection.active is not active:
        viewer.layers.selection.active = active
    if viewer.dims.ndim == ndim and tuple(viewer.dims.point) != point:
        for axis, value in enumerate(point):
            if viewer.dims.point[axis] != value:
                viewer.dims.set_point(axis, value)


def truth_layer(viewer, owner: str | None, shape: tuple[int, ...]):
    """The ground-truth RI layer (kind ``truth``) of the acquisition ``owner`` with the volume's ``shape``, or None."""
    if owner is None:
        return None
    for layer in viewer.layers:
        if (layer.metadata.get(META_KIND) == "truth" and layer.metadata.get(META_OWNER) == owner
                and tuple(np.shape(layer.data)) == tuple(shape)):
            return layer
    return None


def truth_error(viewer, acq_layer, ri: np.ndarray, n_background: float) -> float | None:
    """Relative Δn error of ``ri`` against the truth loaded with the acquisition (sample data), or None."""
    from napari_fdt.recon.assess.metrics import relative_delta_n_error

    truth = truth_layer(viewer, acq_layer.metadata.get(META_ID), np.shape(ri))
    if truth is None:
        return None
    nb = np.float32(n_background)
    try:
        return relative_delta_n_error(np.asarray(ri, np.float32) - nb, np.asarray(truth.data, np.float32) - nb)
    except ValueError:  # a homogeneous truth: no relative error
        return None


def results_line(report: dict[str, Any] | None, truth_err: float | None = None) -> str:
    """The run's key numbers in two short lines: image fit and validation error (relative, 0 is perfect); the error
    against a loaded truth and the TV weight chosen; the half-set resolution and the error bound where the run made them."""
    report = report or {}
    first, second = [], []
    fit = report.get("image_fit") or {}
    if "image_relative_error" in fit:
        first.append(f"image fit {fit['image_relative_error']:.3f}")
    val = report.get("validation") or {}
    if val.get("error") is not None:
        first.append(f"validation {val['error']:.3f} ({val.get('n_images', '?')} held-out images)")
    if truth_err is not None:
        second.append(f"Δn error against the truth {truth_err:.3f}")
    reg = report.get("regularisation") or {}
    if reg.get("chosen"):
        second.append(f"TV weight {reg['tv_xy_weight']:g} (chosen)")
    lines = ["result: " + (", ".join(first) if first else "no image fit")]
    if second:
        lines.append(", ".join(second))
    res = report.get("resolution")
    if res:
        from napari_fdt.recon.run.half_sets import describe_bounds

        lines.append(f"resolution (half-set FSC): {describe_bounds(res)}")
    eb = report.get("error_bounds")
    if eb:
        lines.append(f"error bound: mean {eb['mean_bound']:.1e} RI (holds on ~{100 * eb['level']:.0f} % of voxels of simulated "
                     "scenes); red: structure within its bound")
    return "\n".join(lines)


#: |Δn| (RI units) from which a voxel counts as structure in the "cannot believe" view (the bound's benchmark's support)
STRUCTURE_DN = 1e-3


def show_bounds(viewer, bound: np.ndarray, ri: np.ndarray, ri_layer, n_background: float) -> tuple[Any, Any]:
    """Add the error bound (RI units, the volume's grid) beside ``ri_layer`` as two image layers: the bound itself
    (hidden at first), and in red (1 on 0, added over the volume) the structure one cannot believe: |Δn| above
    :data:`STRUCTURE_DN` but not above the bound. Returns both layers (replaced where this RI layer's were shown before)."""
    delta_n = np.abs(np.asarray(ri, dtype=np.float32) - np.float32(n_background))
    bound = np.asarray(bound, dtype=np.float32)
    doubtful = ((delta_n > STRUCTURE_DN) & (delta_n <= bound)).astype(np.uint8)
    names = (f"{ri_layer.name} error bound", f"{ri_layer.name} structure within its bound")
    for name in names:
        if name in viewer.layers:
            viewer.layers.remove(name)
    common = dict(scale=ri_layer.scale, translate=ri_layer.translate, units=ri_layer.units,
                  metadata={META_KIND: "bound", META_OWNER: ri_layer.metadata.get(META_OWNER)})
    high = float(np.quantile(bound, 0.999)) if bound.size else 1.0
    with keep_view(viewer):
        bound_layer = viewer.add_image(bound, name=names[0], colormap="viridis", contrast_limits=(0.0, max(high, 1e-6)),
                                       visible=False, **common)
        doubt_layer = viewer.add_image(doubtful, name=names[1], colormap="red", blending="additive", contrast_limits=(0, 1),
                                       opacity=0.7, **common)
    viewer.layers.selection.active = ri_layer
    return bound_layer, doubt_layer


def camera(viewer):
    """The viewer's camera (``viewer.scene.camera`` from napari 0.9 on, ``viewer.camera`` before)."""
    scene = getattr(viewer, "scene", None)
    return scene.camera if scene is not None and hasattr(scene, "camera") else viewer.camera


def oblique_camera(viewer) -> None:
    """Turn the 3D camera to :data:`OBLIQUE_ANGLES` while it looks straight down the z axis (napari's default on entering
    3D: (0, 0, 0) in napari 0.9, (0, 0, 90) before; any turn about z alone), so a user's own angle is kept."""
    cam = camera(viewer)
    angles = tuple(float(a) for a in cam.angles)
    if abs(angles[0]) < 1e-6 and abs(angles[1]) < 1e-6:
        cam.angles = OBLIQUE_ANGLES
