"""Image models: the differentiable multi-slice model, the envelope model, the slice loop and its kernels,
partial coherence, memory estimates, and batched rendering of images.

Layer 2: built on :mod:`napari_fdt.physics`. See docs/architecture.md.
"""
