"""A whole run: :mod:`~napari_fdt.recon.run.solver` (the loop over coarse-to-fine stages, the default choices plugged
in), :mod:`~napari_fdt.recon.run.session` (an acquisition's run from files to files, one rank of a distributed run),
:mod:`~napari_fdt.recon.run.report` (RI.json), :mod:`~napari_fdt.recon.run.half_sets` (the resolution from two halves
of the images) and :mod:`~napari_fdt.recon.run.family` (a family of runs across TV weights).

May import every other room of :mod:`napari_fdt.recon`; none imports this one.
"""
