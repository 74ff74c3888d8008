"""Optics and the physics of the measurement: parameters, sampling grids, propagation, point sources, obliquity.

Layer 1 (above :mod:`napari_fdt.errors` and :mod:`napari_fdt.device`): pure functions of lengths in µm; imports
nothing else of the package. See docs/architecture.md.
"""
