"""Simulated test scenes: phantoms (letters, beads, cells) and realistic measurements of them.

Layer 3, beside :mod:`napari_fdt.recon` (neither imports the other). See docs/architecture.md.
"""
