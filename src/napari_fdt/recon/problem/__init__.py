"""What a run optimises and how it predicts images: the RI grid (:mod:`~napari_fdt.recon.problem.volume`), the losses,
the coarse-to-fine stages and their models (:mod:`~napari_fdt.recon.problem.stages`; which model each stage runs,
one rule: :mod:`~napari_fdt.recon.problem.stage_spec`; their images
:mod:`~napari_fdt.recon.problem.stage_images`), the batch order, which stages keep sources fixed or run the envelope
model (:mod:`~napari_fdt.recon.problem.stage_roles`), the checks before a run (:mod:`~napari_fdt.recon.problem.preflight`)
and data-parallel groups (:mod:`~napari_fdt.recon.problem.distributed`).

May import ``calibration`` and ``settings``.
"""
