"""Checks of an acquisition and a configuration before a reconstruction allocates anything.

* :func:`warn_about_images`: blank images and saturated pixels (FDTWarning), which the intensity model
  cannot explain;
* :func:`warn_about_sampling`: sampling problems of the acquisition's grid for these sources (FDTWarning);
* :func:`check_memory`: refuse (FDTInputError) a batch whose finest multi-slice stage would not fit in the
  device's free memory, and say which batch size would.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from napari_fdt.data.acquisition import Acquisition
from napari_fdt.data.mapped import chunks
from napari_fdt.errors import FDTInputError, FDTWarning
from napari_fdt.physics.grid import plan_for_sources
from napari_fdt.recon.problem.stage_images import stays_on_host
from napari_fdt.recon.settings.config import SolverConfig

#: Share of the device's free memory a run may plan to use (the rest: allocator slack, other tensors).
USABLE_SHARE = 0.9

__all__ = ["warn_about_images", "warn_about_sampling", "held_on_device", "coherence_mask_bytes", "finest_stage_bytes", "check_memory", "finest_stage_fits"]


def warn_about_images(acquisition: Acquisition, stacklevel: int = 3) -> None:
    """Warn (FDTWarning) about blank images and saturated pixels, which the intensity model cannot explain.

    ``stacklevel`` points the warning at the caller's caller (the code that made the reconstruction).
    """
    imgs = acquisition.images
    n = imgs.shape[0]
    parts = list(chunks(imgs))  # a memory-mapped stack is read in chunks, without a temporary of its size
    peaks = np.concatenate([imgs[s].reshape(s.stop - s.start, -1).max(axis=1) for s in parts])
    blank = np.flatnonzero(peaks <= 0)
    if blank.size:
        listed = ", ".join(map(str, blank[:10])) + (" …" if blank.size > 10 else "")
        warnings.warn(f"images: {blank.size} of {n} images are blank (no positive pixel): {listed}; they carry no "
                      "information and their gain goes to about 0: drop them from the acquisition", FDTWarning, stacklevel=stacklevel)
    top = np.iinfo(imgs.dtype).max if imgs.dtype.kind == "u" else float(peaks.max())
    if top > 0:
        at_top = sum(int(np.count_nonzero(imgs[s] == top)) for s in parts)
        if at_top > max(10, 1e-3 * imgs.size):
            warnings.warn(f"images: {at_top} pixels ({100 * at_top / imgs.size:.2f} %) sit at the maximum value {top:g}: "
                          "saturated pixels break the intensity model; mask them or re-acquire with less exposure",
                          FDTWarning, stacklevel=stacklevel)


def warn_about_sampling(acquisition: Acquisition, sources_um: np.ndarray) -> None:
    """Warn (FDTWarning, from :func:`napari_fdt.physics.grid.plan_for_sources`) about sampling problems for ``sources_um`` (N, 3) µm."""
    plan_for_sources(acquisition.optics, acquisition.image_shape, sources_um)


def images_on_device(acquisition: Acquisition, device_type: str) -> int:
    """Bytes the measured images take on the device: on a GPU the whole stack as float32; on the CPU none beyond a batch
    (they are read from the acquisition's array, :mod:`napari_fdt.recon.problem.stage_images`)."""
    h, w = acquisition.image_shape
    return 0 if stays_on_host(device_type) else 4 * acquisition.n_images * h * w


def held_on_device(acquisition: Acquisition, config: SolverConfig, device_type: str) -> int:
    """Bytes the finest stage holds on its device whatever its batch: the images (:func:`images_on_device`) and the
    coherence masks (:func:`coherence_mask_bytes`)."""
    return images_on_device(acquisition, device_type) + coherence_mask_bytes(acquisition, config)


def coherence_mask_bytes(acquisition: Acquisition, config: SolverConfig) -> int:
    """Bytes of the finest stage's coherence masks where ``coherence`` uses them: (N, h, w) float32 on the stage's
    device, held for the whole stage (0 otherwise)."""
    if config.coherence not in ("mask", "mask+spectral"):
        return 0
    factor = min(s.factor for s in config.stages)
    h, w = acquisition.image_shape
    return 4 * acquisition.n_images * (h // factor) * (w // factor)


def finest_stage_bytes(acquisition: Acquisition, config: SolverConfig, sources_um: np.ndarray, n_wavelengths: int = 1,
                       device_type: str = "cuda", batch: int | None = None):
    """Bytes the finest multi-slice stage needs on its device (a training step of one batch, and what it holds there:
    :func:`held_on_device`),
    with its window plan, batch and backward mode: ``(bytes, plan, batch, mode)``. ``sources_um`` (N, 3) µm set the
    window; ``batch`` (None: the stage's) the images of the step."""
    from napari_fdt.model.memory import grid_is_unitary, leanest_mode, split_training_bytes, training_bytes
    from napari_fdt.model.oversampled import fine_optics, fine_plan
    from napari_fdt.model.split_field import split_plan
    from napari_fdt.recon.problem.stage_spec import stage_spec
    from napari_fdt.recon.problem.stages import camera_model, config_uses_split_field, multislice_plan

    cfg, o, full_shape = config, acquisition.optics, acquisition.image_shape
    finest_index = min(range(len(cfg.stages)), key=lambda i: cfg.stages[i].factor)
    camera = camera_model(cfg, acquisition)
    spec = stage_spec(cfg, finest_index, "multislice", camera.parts_on(), camera)  # as the first pass runs it (no part chosen)
    factor = spec.factor
    _, opt, _, plan = multislice_plan(o, factor, full_shape, sources_um)
    if batch is None:
        batch = min(cfg.stage_batch(finest_index), acquisition.n_images)
    images = held_on_device(acquisition, cfg, device_type)
    screens = o.n_slices * spec.screens_per_slice  # ("auto" sub-slices: one screen)
    if config_uses_split_field(cfg, device_type, factor, plan, opt, spec.pupil_edge, pixel_integration=spec.pixel_integration):
        if spec.fine_grid:  # the split window of the field's 2x grid
            plan, opt = fine_plan(plan), fine_optics(opt)
        plan = split_plan(plan, opt)  # the split model's loop runs on plain autograd
        need = split_training_bytes(plan.padded_shape, plan.image_shape, screens, batch, n_wavelengths,
                                    spec.pixel_integration)
        return need + images, plan, batch, "autograd (split field)"
    mode = cfg.backward_mode
    if mode == "auto":  # auto falls back to the leanest mode when one field per slice does not fit
        mode = leanest_mode(grid_is_unitary(opt.pixel_size_um, o.n_background, o.wavelength_um))
    if spec.fine_grid:  # the field on a grid twice as fine
        plan = fine_plan(plan)
    return (training_bytes(plan.padded_shape, screens, batch, n_wavelengths, mode, spec.pixel_integration) + images,
            plan, batch, mode)


def finest_stage_fits(acquisition: Acquisition, config: SolverConfig, sources_um: np.ndarray, device: torch.device,
                      n_wavelengths: int) -> tuple[bool, float]:
    """Whether the finest stage of ``config`` fits in 90 % of the device's free memory (True where that is unknown), and
    the GiB it needs (:func:`finest_stage_bytes`)."""
    from napari_fdt.device import available_bytes

    need = finest_stage_bytes(acquisition, config, sources_um, n_wavelengths, torch.device(device).type)[0]
    free = available_bytes(device)
    return (free is None or need <= USABLE_SHARE * free), need / 2.0**30


def check_memory(acquisition: Acquisition, config: SolverConfig, sources_um: np.ndarray, device: torch.device,
                 n_wavelengths: int) -> None:
    """Refuse, before any allocation, a batch whose finest multi-slice stage would not fit in memory.

    ``sources_um``: (N, 3) µm (they set the window); ``n_wavelengths``: of the spectral sum (1 without).
    Raises :class:`~napari_fdt.errors.FDTInputError` (field ``batch_size``) with the batch size that would fit.
    """
    from napari_fdt.device import available_bytes

    free = available_bytes(device)
    if free is None:
        return
    need, plan, batch, mode = finest_stage_bytes(acquisition, config, sources_um, n_wavelengths, torch.device(device).type)
    o, k = acquisition.optics, n_wavelengths
    images = held_on_device(acquisition, config, torch.device(device).type)
    if need <= USABLE_SHARE * free:
        return
    one = finest_stage_bytes(acquisition, config, sources_um, n_wavelengths, torch.device(device).type, batch=1)[0] - images
    fits = int((USABLE_SHARE * free - images) // max(1, one))
    gib = 2.0**30
    fix = (f"lower batch_size to {fits}" if fits >= 1 else
           "crop the images, use fewer slices or fewer wavelengths, or a device with more memory")
    if "split" in mode:  # the split model keeps each screen's source field: the full window may need less
        fix += ', or set field_window "full"'

    raise FDTInputError(
        "batch_size",
        f"a batch of {batch} images needs about {need / gib:.1f} GiB on {device} "
        f"({plan.padded_shape[0]}x{plan.padded_shape[1]} window, {o.n_slices} slices, {k} wavelength(s), "
        f"backward mode {mode}); "
        f"{free / gib:.1f} GiB are free",
        fix,
    )
