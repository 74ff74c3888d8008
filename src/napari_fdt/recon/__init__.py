"""Reconstruction: settings, the RI volume, losses, coarse-to-fine stages, source fitting, the solver, data-parallel
runs, reports and metrics.

Layer 3, beside :mod:`napari_fdt.sim` (neither imports the other). See docs/architecture.md.
"""
