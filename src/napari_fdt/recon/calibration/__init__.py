"""What is fitted beside the volume: :mod:`~napari_fdt.recon.calibration.calibration` (source positions, the depth
offset, gains, optical scales, pupil and aberrations, with their optimiser) and
:mod:`~napari_fdt.recon.calibration.source_fit` (the sources' first positions from the images).

May import ``settings``.
"""
