"""What the widgets compute, as plain functions of the core (no Qt, no napari): previews and diagnostics.

Every function here calls the same forward model, masks and solver state as ``fdt``; none adds physics.
Lengths in µm; images in the acquisition's intensity units.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.errors import FDTInputError
from napari_fdt.model.coherence import coherence_masks
from napari_fdt.model.forward import MultiSliceModel
from napari_fdt.model.gain import least_squares_gain
from napari_fdt.model.render import iter_batches, render_images
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.physics.optics import Optics

__all__ = ["illumination_coverage", "forward_preview", "mask_stack", "predicted_vs_measured", "check_index"]


def check_index(index: int, n_images: int) -> int:
    """``index`` as an int in ``[0, n_images)``, else :class:`FDTInputError`."""
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= int(index) < n_images:
        raise FDTInputError("image", f"index {index!r} is not an image of the stack (0 … {n_images - 1})",
                            f"choose an image between 0 and {n_images - 1}")
    return int(index)


def illumination_coverage(optics: Optics, image_shape: tuple[int, int], sources_um: np.ndarray) -> np.ndarray:
    """How many sources light each voxel within the pupil: (n_slices, H, W) int32.

    A voxel centred at height z above the volume's bottom face (z = (k + ½)·dz) and lateral position
    (x, y) (``docs/format.md``) is lit by source i = [x_i, y_i, depth_i] when its lateral distance from
    the source is at most ``(depth_i + z)·tan(asin(NA/n_b))``: it lies inside the cone of rays the pupil
    accepts. Voxels lit by few sources are poorly constrained by the data.
    """
    src = np.asarray(sources_um, dtype=np.float64).reshape(-1, 3)
    h, w = (int(s) for s in image_shape)
    dx, dz = optics.pixel_size_um, optics.slice_spacing_um
    y = (np.arange(h) - h // 2) * dx
    x = (np.arange(w) - w // 2) * dx
    z = (np.arange(optics.n_slices) + 0.5) * dz
    tan = math.tan(math.asin(optics.na / optics.n_background))
    out = np.zeros((optics.n_slices, h, w), dtype=np.int32)
    for xs, ys, depth in src:
        r2 = (y[:, None] - ys) ** 2 + (x[None, :] - xs) ** 2  # (H, W)
        radius = (depth + z) * tan  # (n_slices,)
        out += r2[None, :, :] <= (radius * radius)[:, None, None]
    return out


def forward_preview(
    acq: Acquisition,
    sources_um: np.ndarray,
    index: int,
    delta_n: np.ndarray | None = None,
    *,
    device: str = "cpu",
) -> tuple[np.ndarray, np.ndarray, float]:
    """Predict image ``index`` for the current parameters; return ``(predicted, measured, gain)``.

    ``delta_n`` (n_slices, H, W) is the contrast (RI − n_b); None is the homogeneous medium. The prediction
    is the forward model's image of source ``index`` times the least-squares gain against the measurement
    (a fluorophore's brightness is unknown), both (H, W) float32.
    """
    index = check_index(index, acq.n_images)
    o = acq.optics
    src = np.asarray(sources_um, dtype=np.float64).reshape(-1, 3)[index : index + 1]
    shape = (o.n_slices, *acq.image_shape)
    if delta_n is None:
        dn = np.zeros(shape, dtype=np.float32)
    else:
        dn = np.asarray(delta_n, dtype=np.float32)
        if dn.shape != shape:
            raise FDTInputError("ri", f"volume shape {dn.shape} does not match the acquisition's {shape}",
                                "use an RI layer of this acquisition (or none for the homogeneous medium)")
    model = MultiSliceModel(o, plan_for_sources(o, acq.image_shape, src), device=device)
    pred = render_images(model, dn, src)[0].astype(np.float64)
    meas = np.asarray(acq.images[index], dtype=np.float64)
    gain = float(least_squares_gain(torch.from_numpy(pred), torch.from_numpy(meas)))
    return (pred * gain).astype(np.float32), meas.astype(np.float32), gain


def mask_stack(acq: Acquisition, sources_um: np.ndarray, threshold: float = 0.5, *, device: str = "cpu",
               batch_size: int = 16) -> np.ndarray:
    """The solver's coherence masks (:func:`napari_fdt.model.coherence.coherence_masks`) of every source, (N, H, W) float32 0/1."""
    o = acq.optics
    src = np.asarray(sources_um, dtype=np.float64).reshape(-1, 3)
    if src.shape[0] != acq.n_images:
        raise FDTInputError("sources", f"{src.shape[0]} sources for {acq.n_images} images", "give one source per image")
    model = MultiSliceModel(o, plan_for_sources(o, acq.image_shape, src), device=device)
    out = np.empty((src.shape[0], *acq.image_shape), dtype=np.float32)
    for sl in iter_batches(src.shape[0], batch_size):
        out[sl] = coherence_masks(model, src[sl], threshold=threshold).cpu().numpy()
    return out


def predicted_vs_measured(rec, index: int) -> tuple[np.ndarray, np.ndarray]:
    """Image ``index`` as the reconstruction predicts it (calibrated sources, gains and optics, full grid) and as measured.

    ``rec`` is a :class:`~napari_fdt.recon.run.solver.Reconstructor` that holds a volume; this is one image of
    :func:`napari_fdt.recon.run.report.evaluate_images`. Returns two (H, W) float32 images in the acquisition's units.
    """
    acq = rec.acquisition
    index = check_index(index, acq.n_images)
    if rec.volume is None:
        raise FDTInputError("reconstruction", "holds no volume yet", "run a reconstruction first")
    pred = rec.predict([index])[0]
    return pred.astype(np.float32), np.asarray(acq.images[index], dtype=np.float32)
