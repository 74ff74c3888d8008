"""Memory estimates, so that a run too large for the device is refused before anything is allocated.

Training keeps, through autograd, a few complex fields per slice and image. Measured on CPU (peak
resident memory of one forward + backward, torch 2.13, complex64): 12–32 bytes per window pixel, per
slice, per image (allocator caching makes the figure vary); PHYSICS.md gives about 9 on CUDA. We use the
upper figure, 32, so a refusal means the run would almost surely not fit.
"""

from __future__ import annotations

import os

import torch

__all__ = ["BYTES_PER_PIXEL_SLICE_IMAGE", "training_bytes", "available_bytes"]

#: Upper estimate of autograd memory, bytes per window pixel per slice per image (complex64).
BYTES_PER_PIXEL_SLICE_IMAGE = 32


def training_bytes(padded_shape: tuple[int, int], n_slices: int, batch: int, n_wavelengths: int = 1) -> int:
    """Estimated peak bytes of one training iteration of the multi-slice model (forward + backward)."""
    pixels = int(padded_shape[0]) * int(padded_shape[1])
    per_image = BYTES_PER_PIXEL_SLICE_IMAGE * pixels * max(1, int(n_slices))
    kernels = 64 * pixels  # cached kernels, window, pupil
    return per_image * int(batch) * max(1, int(n_wavelengths)) + kernels


def available_bytes(device: torch.device) -> int | None:
    """Free memory on ``device`` in bytes (CUDA: free device memory; CPU: available RAM on Linux), or None."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(free)
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


#: Upper estimate of inference memory (``torch.no_grad``: ``fdt forward``, ``fdt simulate``), bytes per window
#: pixel per image of a batch. Inference keeps a few complex fields per image, not one per slice: measured on CPU
#: (``benchmarks/forward_memory.py``: peak resident growth of one ``render_images`` call, torch 2.13, complex64)
#: 26–54 bytes per pixel per image for windows of 1024² and 2048², batches of 1–16 and 4–32 slices, all included;
#: a least-squares fit gives 27 per pixel per image plus 4.6 per pixel per slice (the padded float32 volume). The
#: same run varies by up to 60 % (120–217 MiB for 1024², 4 slices, batch 4: the allocator keeps or returns
#: 32 MiB blocks), hence the margin.
FORWARD_BYTES_PER_PIXEL_IMAGE = 56


def forward_bytes(padded_shape: tuple[int, int], n_slices: int, batch: int) -> int:
    """Estimated peak bytes of one batch of the multi-slice model without autograd (``fdt forward``, ``fdt simulate``).

    A few complex fields per image (:data:`FORWARD_BYTES_PER_PIXEL_IMAGE` per window pixel), the contrast volume
    padded to the window (float32, 4 bytes per pixel per slice) and the cached kernels (64 bytes per pixel, as in
    :func:`training_bytes`). Unlike training, the cost per image does not grow with the number of slices.
    """
    pixels = int(padded_shape[0]) * int(padded_shape[1])
    return FORWARD_BYTES_PER_PIXEL_IMAGE * pixels * max(1, int(batch)) + 4 * pixels * max(1, int(n_slices)) + 64 * pixels


__all__ += ["FORWARD_BYTES_PER_PIXEL_IMAGE", "forward_bytes"]
