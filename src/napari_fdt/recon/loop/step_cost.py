"""The plan's cost model: the seconds of one iteration from its size, by device and model.

An iteration of a stage costs about ``batch · slices · P · log2 P`` units, ``P`` the pixels of the grid the model's
FFTs run on (the multi-slice window, or the envelope model's padded grid), plus the split-field model's source fields
and obliquity screens per image pixel, times a per-model rate of the device (:data:`SECONDS_PER_UNIT`) plus a
per-iteration overhead (:data:`OVERHEAD_S`). The rates were measured on the bundled sample (docs/benchmarks.md, "The
plan's cost model"); a run corrects them by what it measures (:class:`~napari_fdt.recon.loop.pace.Pace`).
:mod:`napari_fdt.recon.loop.plan` prices its phases with it.
"""

from __future__ import annotations

import math

from napari_fdt.physics.optics import Optics

__all__ = ["SECONDS_PER_UNIT", "OVERHEAD_S", "PILOT_STEP_OVERHEAD_S", "SOURCE_FIELD_UNITS", "OBLIQUITY_UNITS", "iteration_units",
           "envelope_padded_shape"]

#: Seconds per cost unit of one iteration, by (device type, model). CPU: 2 threads of a 2-core AMD EPYC (Zen 5),
#: 2026-11-29, the default runs of the sample, cells, deep and beads (probe off): each stage's
#: measured seconds per iteration over the rates before (5.5e-9 and 1.09e-9, fitted in 2026-11-25/26 on a first-generation
#: EPYC), median 0.90 for the envelope stages (0.73-1.45, 6 stages) and 0.50 for the split multi-slice ones (0.40-0.76,
#: 6 stages, the pupil's pilot 0.46). CUDA: an H100 on 2026-11-26 (docs/decisions/gpu-checklist-h100.md):
#: the sample's finest stage 15.8-21 ms and the demo's 32.6 ms per multi-slice iteration, about 17 ms of it outside the
#: model's step (before: 9 ms, from the November suite rows 10.0, 19.5, 99.5 ms); the envelope model on CUDA (not the
#: default there) is priced like the multi-slice one.
#: ``"split"``: the split-field multi-slice model (the CPU's default where its window is smaller); ``"multislice"``: the
#: multi-slice model on its full window, on the CPU 1.54-2.33x slower per unit than the split model's rate (the
#: finest step run alone, 2026-11-29, measured against 5.5e-10: the sample 217 ms against 138, cells_pupil 149 against
#: 97, cells 130 against 83, the full-size stack's 600² window 2.51 s against 1.08 s); 1.0e-9 puts them at 0.78-1.28x.
SECONDS_PER_UNIT: dict[tuple[str, str], float] = {
    ("cpu", "envelope"): 5.0e-9,
    ("cpu", "split"): 5.5e-10,
    ("cpu", "multislice"): 1.0e-9,
    ("cuda", "envelope"): 6.7e-12,
    ("cuda", "split"): 6.7e-12,
    ("cuda", "multislice"): 6.7e-12,
}
#: Seconds of one iteration that do not scale with its size (kernel launches), by device type.
OVERHEAD_S: dict[str, float] = {"cpu": 0.0, "cuda": 1.7e-2}
#: Seconds of one step of the pupil's pilot on the CPU that do not scale with its size (the sources' and gains'
#: updates, Python), on the machine of :data:`SECONDS_PER_UNIT`: the sample's pilot took 10.7 ms per step where its
#: units give 3.5 ms (2026-11-29; on the first-generation EPYC of 2026-11-26 night 35 ms against 10 ms); on the GPU the
#: iteration's overhead (:data:`OVERHEAD_S`) stands for it.
PILOT_STEP_OVERHEAD_S = 0.007


#: Cost units of the split-field model's source field at one image pixel of one screen of one image (the radial
#: tables' interpolation and phase, forward and backward): the sample's finest stage on 2 CPU cores, 0.134 s per
#: iteration on a 192² window against 0.078 s for its FFTs alone (2026-11-26).
SOURCE_FIELD_UNITS = 43.0
#: Cost units of the split-field model's per-source obliquity screen at one image pixel of one screen of one image
#: (its secant, phase and screen update per source, forward and backward): the finest stage with 2 sub-slices on 2 CPU
#: cores (the machine of :data:`SECONDS_PER_UNIT`), obliquity's extra milliseconds per step over batch x screens x image
#: pixels: 24.5 (fibres_thick, 64² image, 14 ms of 71), 19.6 (the sample, 96², 25 ms of 84), 17.5 (cells_fine, 64², 10 ms
#: of 54); 2026-11-29.
OBLIQUITY_UNITS = 20.0


def iteration_units(batch: int, n_slices: int, fft_shape: tuple[int, int], pixel_integration: bool = False,
                    source_pixels: int = 0, camera_points: int = 0) -> float:
    """Cost units of one iteration: ``batch · (n_slices + s_pi) · P · log2 P`` with ``P`` the pixels of ``fft_shape``,
    plus ``batch · (n_slices · source_pixels + camera_points) ·`` :data:`SOURCE_FIELD_UNITS` for the split-field
    model's source fields at the screens (``source_pixels``: the image's pixels) and at the camera (``camera_points``:
    the image's pixels, or the fine grid's over the image and its margin with pixel integration); 0 for the other
    models. (The split model's pixel integration on the sample: 94 ms more per step, 41 ms of FFTs and 45 ms of camera
    field in these units.)

    A slice costs about 4 FFTs of the window (a forward and an adjoint transform pair); the camera's pixel integration
    (multi-slice model) adds 4 FFTs on a grid twice as fine (4P pixels), ``s_pi = 4·log2(4P)/log2(P)`` slices' worth
    (measured: 1.77× the step at 256², 6 slices, where this gives 1.75×)."""
    p = max(2, int(fft_shape[0]) * int(fft_shape[1]))
    extra = 4.0 * math.log2(4 * p) / math.log2(p) if pixel_integration else 0.0
    sources = float(batch) * (float(n_slices) * float(source_pixels) + float(camera_points)) * SOURCE_FIELD_UNITS
    return float(batch) * (float(n_slices) + extra) * p * math.log2(p) + sources


def envelope_padded_shape(optics: Optics, image_shape: tuple[int, int], factor: int) -> tuple[int, int]:
    """The padded grid (h, w) the envelope model of a stage of ``factor`` works on (as
    :class:`~napari_fdt.model.envelope.EnvelopeModel` pads it)."""
    from napari_fdt.model.envelope import envelope_window

    return envelope_window(optics, (image_shape[0] // factor, image_shape[1] // factor), factor)[0]
