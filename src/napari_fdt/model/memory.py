"""Memory estimates, so that a run too large for the device is refused before anything is allocated.

The slice loop keeps what its backward mode needs (:func:`napari_fdt.model.slice_loop.loop_bytes`: one
complex field per slice and image in ``"stored"`` mode, a few per image in ``"reversible"`` mode,
about 2·√N per image in ``"checkpoint"`` mode); the rest of one training iteration (source spectrum,
exit propagation, intensity, loss and their gradients) keeps about :data:`GRAPH_FIELDS_PER_IMAGE`
fields per image. Plain autograd (``backward_mode="autograd"``) keeps 12–32 bytes per window pixel,
per slice, per image (measured on CPU, torch 2.13); we use the upper figure. Measured peaks against
these estimates: ``docs/benchmarks.md``.
"""

from __future__ import annotations

from napari_fdt.model.slice_loop import leanest_mode, loop_bytes

__all__ = ["BYTES_PER_PIXEL_SLICE_IMAGE", "GRAPH_FIELDS_PER_IMAGE", "FULL_BYTES_PIXEL_INTEGRATION", "training_bytes", "split_training_bytes", "leanest_mode",
           "grid_is_unitary", "FORWARD_BYTES_PER_PIXEL_IMAGE", "forward_bytes"]

#: Upper estimate of plain-autograd memory, bytes per window pixel per slice per image (complex64).
BYTES_PER_PIXEL_SLICE_IMAGE = 32
#: Complex fields per image kept outside the slice loop during one iteration (upper estimate).
GRAPH_FIELDS_PER_IMAGE = 10


def grid_is_unitary(pixel_size_um: float, n_background: float, wavelength_um: float, slack: float = 0.02) -> bool:
    """True when every frequency of a grid of this pixel size propagates (no evanescent corner):
    the propagator then has modulus 1 everywhere and the reversible backward mode is exact.
    ``slack``: the pixel may shrink by this fraction (self-calibration) and the answer still hold."""
    f_corner2 = 2.0 * (0.5 / (pixel_size_um * (1.0 - slack))) ** 2
    return f_corner2 < (n_background / wavelength_um) ** 2 * (1.0 - 1e-9)


#: The camera's pixel integration in the full-window model (the exit field on a grid twice as fine, its intensity and
#: their gradients), bytes per window pixel per image: an upper estimate of the extra peak resident growth of a training
#: step with it on (``python -m benchmarks run training_memory``; torch 2.13, complex64, batch 16, 2 CPU cores,
#: 2026-11-29, the same step reads up to 20 % apart from run to run): the sample 154-180 (324x360 window, 8 slices),
#: cells_pupil 113-175 (256², 6), the full-size stack 70-88 (600², 14 slices). Before it was counted, the estimate was
#: 0.57-0.76x the measured step with pixel integration on (docs/hard_cases.md).
FULL_BYTES_PIXEL_INTEGRATION = 256


def training_bytes(
    padded_shape: tuple[int, int],
    n_slices: int,
    batch: int,
    n_wavelengths: int = 1,
    mode: str = "stored",
    pixel_integration: bool = False,
) -> int:
    """Estimated peak bytes of one training iteration of the multi-slice model (forward + backward).

    ``mode`` is the slice loop's backward mode (``"stored"``, ``"reversible"``, ``"checkpoint"`` or
    ``"autograd"``); complex64 fields. Each wavelength of a spectral model keeps its own graph.
    ``pixel_integration``: the camera's pixel means on (:data:`FULL_BYTES_PIXEL_INTEGRATION` per window pixel per image).
    """
    pixels = int(padded_shape[0]) * int(padded_shape[1])
    n = max(1, int(n_slices))
    b = int(batch) * max(1, int(n_wavelengths))
    field = 8 * pixels
    camera = FULL_BYTES_PIXEL_INTEGRATION * pixels * b if pixel_integration else 0
    if mode == "autograd":
        per_image = BYTES_PER_PIXEL_SLICE_IMAGE * pixels * n
        return per_image * b + 64 * pixels + camera
    volume = 5 * 4 * pixels * n  # Δn, phases, their gradients, Adam moments (float32)
    return loop_bytes(mode, field, n, b) + GRAPH_FIELDS_PER_IMAGE * field * b + volume + 64 * pixels + camera


#: The split-field model's training memory (its loop on plain autograd), bytes per screen per image: per pixel of its
#: window (the loop's fields) and per pixel of the image (the sources' fields: the tables' lookups keep ~40 bytes per
#: point for the backward); per window pixel per image with pixel integration (fields on the 2x grid). Upper estimates
#: of the peak resident growth of one training step (torch 2.13, complex64, batch 16, 2026-11-26; /proc VmHWM; the same
#: step reads differently from run to run, as the allocator keeps or returns blocks): the sample 182 and 270 MiB (192²
#: window, 96² image, 8 screens; estimate 320), letters128 324 and 455 MiB (200², 128², 10; 569), cells_pupil with pixel
#: means 310 and 366 MiB (180², 96², 6; 462).
SPLIT_BYTES_PER_WINDOW_PIXEL = 36
SPLIT_BYTES_PER_IMAGE_PIXEL = 140
SPLIT_BYTES_PIXEL_INTEGRATION = 480


def split_training_bytes(window_shape: tuple[int, int], image_shape: tuple[int, int], screens: int, batch: int,
                         n_wavelengths: int = 1, pixel_integration: bool = False) -> int:
    """Estimated peak bytes of one training iteration of :class:`~napari_fdt.model.split_field.SplitFieldModel`
    (forward + backward) on a ``window_shape`` window for ``image_shape`` images with ``screens`` screens."""
    window = int(window_shape[0]) * int(window_shape[1])
    image = int(image_shape[0]) * int(image_shape[1])
    n = max(1, int(screens))
    per_image = n * (SPLIT_BYTES_PER_WINDOW_PIXEL * window + SPLIT_BYTES_PER_IMAGE_PIXEL * image)
    if pixel_integration:
        per_image += SPLIT_BYTES_PIXEL_INTEGRATION * window
    volume = 5 * 4 * image * n  # Δn, phases, their gradients, Adam moments (float32)
    return per_image * int(batch) * max(1, int(n_wavelengths)) + volume + 64 * window


#: Upper estimate of inference memory (``torch.no_grad``: ``fdt forward``, ``fdt simulate``), bytes per window
#: pixel per image of a batch. Inference keeps a few complex fields per image, not one per slice: measured on CPU
#: (``benchmarks/forward_memory.py``: peak resident growth of one ``render_images`` call, torch 2.13, complex64)
#: 26–54 bytes per pixel per image for windows of 1024² and 2048², batches of 1–16 and 4–32 slices, all included;
#: a least-squares fit gives 27 per pixel per image plus 4.6 per pixel per slice (the padded float32 volume). The
#: same run varies by up to 60 % (120–217 MiB for 1024², 4 slices, batch 4: the allocator keeps or returns
#: 32 MiB blocks), hence the margin. (A reading of 391 MiB on a CI machine came from the measurement: ``ru_maxrss``
#: carries a parent process's peak into its child; ``benchmarks/forward_memory.py`` reads ``VmHWM`` now.)
FORWARD_BYTES_PER_PIXEL_IMAGE = 56


def forward_bytes(padded_shape: tuple[int, int], n_slices: int, batch: int) -> int:
    """Estimated peak bytes of one batch of the multi-slice model without autograd (``fdt forward``, ``fdt simulate``).

    A few complex fields per image (:data:`FORWARD_BYTES_PER_PIXEL_IMAGE` per window pixel), the contrast volume
    padded to the window (float32, 4 bytes per pixel per slice) and the cached kernels (64 bytes per pixel, as in
    :func:`training_bytes`). Unlike training, the cost per image does not grow with the number of slices.
    """
    pixels = int(padded_shape[0]) * int(padded_shape[1])
    return FORWARD_BYTES_PER_PIXEL_IMAGE * pixels * max(1, int(batch)) + 4 * pixels * max(1, int(n_slices)) + 64 * pixels
