"""What is fitted beside the volume: :mod:`~napari_fdt.recon.calibration.calibration` (source positions, the depth
offset, gains, optical scales, pupil and aberrations, with their optimiser),
:mod:`~napari_fdt.recon.calibration.source_fit` (the sources' first positions from the images) and
:mod:`~napari_fdt.recon.calibration.adam` (the run's Adam: torch's, stepped without importing the compiler, for the
RI grid, the calibration and the parts' fits).

May import ``settings``.
"""
