"""Acquisitions and files: the in-memory acquisition with its checks, and reading/writing the format (docs/format.md).

Layer 2, beside :mod:`napari_fdt.model` (neither imports the other): built on :mod:`napari_fdt.physics`. No torch.
See docs/architecture.md.
"""
