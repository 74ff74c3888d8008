"""The background work behind the widgets, with no Qt and no napari: a reconstruction job
(:mod:`~napari_fdt.napari.jobs.job`, :mod:`~napari_fdt.napari.jobs.family_job`), its own process
(:mod:`~napari_fdt.napari.jobs.remote_job` starts :mod:`~napari_fdt.napari.jobs.compute_process`), small computations
(:mod:`~napari_fdt.napari.jobs.compute`) and resuming from checkpoints (:mod:`~napari_fdt.napari.jobs.resume`).
Imports no widget.
"""
