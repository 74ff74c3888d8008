"""The solver's settings (:mod:`~napari_fdt.recon.settings.config`), the finest stage's step schedule
(:mod:`~napari_fdt.recon.settings.schedule`) and the ``fdt reconstruct`` line of a run read back from its report
(:mod:`~napari_fdt.recon.settings.command`). The bottom room: imports no other.
"""
