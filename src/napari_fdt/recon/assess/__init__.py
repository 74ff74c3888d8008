"""Numbers about a volume or its images: :mod:`~napari_fdt.recon.assess.validation` (held-out splits, relative image
errors, the best iterate), :mod:`~napari_fdt.recon.assess.metrics` (Δn error, PSNR, SSIM against a truth) and
:mod:`~napari_fdt.recon.assess.fsc` (Fourier shell correlation). Functions of arrays; no run state.

May import ``problem``, ``calibration`` and ``settings``.
"""
